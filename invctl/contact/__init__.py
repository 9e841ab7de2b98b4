"""Contact mechanics of Lagrangian complementarity systems (000 Sect. 2-3, 5).

Import from the submodules: :mod:`~invctl.contact.lcp` (exact and
branch-free LCP solvers), :mod:`~invctl.contact.mechanics` (gap functions,
Delassus matrices (7)-(8), contact LCP, Moreau's impact law (4)-(5), energy
loss (39)), :mod:`~invctl.contact.linkage` (planar linkages with joint
clearances: the open system from bodies and joints),
:mod:`~invctl.contact.structure` (independent subsystems, their actuation,
the contact pattern (2)-(3)), :mod:`~invctl.contact.reduction` (the
clearance-free model (6), ``M_wc``), :mod:`~invctl.contact.equilibria`
(rest points of the closed loop, (40)-(41)).
"""
