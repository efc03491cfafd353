"""Run the demo: ``python -m ctid_ros.demo`` (what ``make demo`` does)."""

import sys

from ctid_ros.demo.wheel import main

__all__: list = []

sys.exit(main())
