import sys

from matspray.cli import main

sys.exit(main())
