"""Generic linear algebra the solid and the fluid share: banded Cholesky factors and solves of
sparse SPD matrices (`banded`), the DCT-diagonalised Neumann Poisson solves (`dct`) and batched
preconditioned conjugate gradients (`pcg`)."""
