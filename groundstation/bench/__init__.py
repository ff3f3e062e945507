"""Benchmarks: paper reproduction (``paper2d``), speed-vs-accuracy charts, stability sweeps.

The commands' options and entries are in ``groundstation.cli.bench``; the data generators and
measures here are pure.
"""
