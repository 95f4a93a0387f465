import sys

from fedlgr.cli import main

sys.exit(main())
