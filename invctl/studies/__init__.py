"""Studies: speed-versus-accuracy trade-offs and parameter sweeps. Import from the submodules."""
