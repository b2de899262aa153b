import sys

from vastray.cli import main

sys.exit(main())
