"""`python -m usmswitch.client.ctl`: usmswitchctl."""

import sys

from .main import main

sys.exit(main())
