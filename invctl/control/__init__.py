"""Controllers: funnel (003 Sect. 5), switched motion/force (002), PD+/pre-loading (000). Import from the submodules."""
