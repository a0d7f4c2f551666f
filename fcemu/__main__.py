import sys

from fcemu.cli import main

sys.exit(main())
