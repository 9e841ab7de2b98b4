"""Shipped scenes: one module per scene, each with ``PARAMS``, ``build`` and ``COMMANDS``."""
