"""fishsim: a fast, fully differentiable simulator for soft swimming robots in water.

A 2D soft fish (FEM, differentiable projective dynamics) swims in a fluid computed either by a
physics-trained U-Net (HydroNet) or by a numerical Navier-Stokes solver on the same MAC grid,
linked by a differentiable immersed-boundary coupling layer (Nava et al., ICML 2022).
"""

__version__ = "0.1.0"
