"""Stability analysis: conewise-linear systems (002), Lyapunov monitoring (000). Import from the submodules."""
