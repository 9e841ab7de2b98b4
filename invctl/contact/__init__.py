"""Contact mechanics of Lagrangian complementarity systems (000 Sect. 2-3).

Import from the submodules: :mod:`~invctl.contact.lcp` (exact and
branch-free LCP solvers), :mod:`~invctl.contact.mechanics` (gap functions,
Delassus matrices (7)-(8), contact LCP, Moreau's impact law (4)-(5), energy
loss (39)).
"""
