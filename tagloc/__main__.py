import sys

from tagloc.cli import main

sys.exit(main())
