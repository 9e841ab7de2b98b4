"""Studies and the commands on top of them, written once for every scene.

``commands`` (the front door of every ``invctl`` command), the scene kinds' commands
(``tracking`` + ``tracking_report`` for 003, ``contact`` for 000, ``switched`` + ``switched_report``
for 002), declared ``reports``, ``animation`` of saved runs, speed-versus-accuracy trade-offs
(``tradeoff``, ``tradeoff_specs``), the time-step study (``timestep``) and parameter sweeps
(``sweep``, ``robustness``). Import from the submodules."""
