"""`python -m src.bench`: see `src.bench.cli`."""

from src.bench.cli import main

raise SystemExit(main())
