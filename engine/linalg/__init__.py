"""Linear algebra the step kernels share, each piece written once: lanes (barriers, sums and maxima
over a world's lanes, the cycle clock), dense (Cholesky factors and solves of the dense per-world
matrix: tile kernels and per-lane functions), sparse_analysis (host: the sparse factor's order,
pattern and schedules, once per topology) and sparse (device: the matrix, factor and solves on
that pattern)."""
