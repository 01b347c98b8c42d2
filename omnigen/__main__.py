import sys

from omnigen.cli import main

sys.exit(main())
