"""fcemu: a MAVLink flight-controller firmware emulator for neural and PID rate control."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("fcemu")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+src"
