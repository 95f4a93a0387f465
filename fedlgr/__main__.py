import sys

from fedlgr.shell.cli import main

sys.exit(main())
