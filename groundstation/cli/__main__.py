"""``python -m groundstation.cli ...`` = ``groundstation ...``."""

from groundstation.cli import main

raise SystemExit(main())
