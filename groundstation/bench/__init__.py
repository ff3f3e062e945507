"""Benchmarks: paper reproduction (``paper2d``), speed-vs-accuracy charts, stability sweeps.

Each command module provides ``add_arguments(parser)`` and ``run(args) -> int``
(see ``groundstation.cli``); the data generators and measures they use are pure.
"""
