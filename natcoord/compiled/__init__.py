"""The compiled core: numba loops per formulation, step control, sparsity plans, codegen."""
