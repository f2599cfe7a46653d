import sys

from dvfb.cli import main

sys.exit(main())
