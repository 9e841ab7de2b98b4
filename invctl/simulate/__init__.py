"""Simulation: closed-loop DAEs, event-located switching, nonsmooth time-stepping. Import from the submodules."""
