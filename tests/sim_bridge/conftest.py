"""The lockstep link's fixtures: a twin server on loopback, and a client behind a lossy relay."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from fcemu.sim_bridge.link import UdpTwinClient
from fcemu.sim_bridge.twin import Twin
from fcemu.sim_bridge.twin_server import UdpTwinServer
from tests.sim_bridge.link_rig import LossyProxy, client_of


@pytest.fixture
def server() -> Iterator[UdpTwinServer]:
    with UdpTwinServer(Twin(rig="rig"), session_timeout=5.0) as srv:
        yield srv


@pytest.fixture
def proxied(server: UdpTwinServer,
            request: pytest.FixtureRequest) -> Iterator[tuple[UdpTwinClient, LossyProxy]]:
    proxy = LossyProxy(server.address, **request.param)
    client = client_of(proxy.address)
    yield client, proxy
    client.close()
    proxy.close()
