"""Forward dynamics: the Solver, the formulations (index-1, Maggi, index-3) and their loops."""
