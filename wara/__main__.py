import sys

from wara.cli import main

sys.exit(main())
