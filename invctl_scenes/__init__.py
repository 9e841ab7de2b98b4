"""Shipped scenes: one module per scene, each declaring ``SCENE = invctl.scenes.Scene(...)``."""
