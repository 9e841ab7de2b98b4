"""Figures for results and studies. Import from the submodules."""
