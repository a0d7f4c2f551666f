#!/usr/bin/env python3
"""Take off, hover, flip, land over MAVLink with pymavlink: the script `fcemu demo` flies.

It ships inside fcemu as `sitl/demo_flight.py` (read it there); this file runs it from a
checkout (`make demo` installs fcemu in `.venv`).
With fcemu installed, `python -m fcemu.sitl.demo_flight` does the same.

    fcemu sitl --controller pid            # in one terminal
    python examples/pymavlink_flip.py      # in another
"""

import sys

from fcemu.sitl.demo_flight import main

if __name__ == "__main__":
    sys.exit(main())
