"""Maintainer scripts: benchmarks against earlier revisions, GPU checks and their report,
measurements and generators. Run from the repository root as ``python -m tools.NAME``."""
