import sys

from .aero import main

sys.exit(main())
