"""Studies and the command glue on top of them: the tracking study of 003 Sect. 6
(``tracking``, ``tracking_commands``), the switched-control study of 002 (``switched``), the
contact scenes of 000 (``contact_commands``, ``timestep``), speed-versus-accuracy trade-offs
(``tradeoff``, ``tradeoff_specs``, ``commands``) and parameter sweeps (``sweep``,
``robustness``). Import from the submodules."""
