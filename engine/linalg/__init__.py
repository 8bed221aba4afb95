"""Linear algebra the step kernels share: dense lane factorizations and solves, sparse factor
analysis (host) and factorization (device), lane reductions and the cycle clock."""
