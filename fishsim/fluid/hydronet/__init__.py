"""HydroNet: the physics-constrained U-Net fluid model (paper Sec. 3.1; Wandel et al. 2021).

unet.py   network, grid-unit scaling, bounded update, ``HydroNetFluid`` (the ``FluidModel``)
loss.py   unsupervised Navier-Stokes + boundary loss (uses ``fishsim.fluid.residual``)
model_file.py ``load_hydronet``: a trained network from its file
scales.py grid units U* = dx/h, A* = dx^2/h, P* = rho U*^2 shared by the net and the loss
config.py settings imported without torch (the CLI's help): pressure choices, ``EvalConfig``,
          ``TrainConfig``, ``NetConfig``, ``PoolConfig``

Its training, evaluation and shipping are fishsim.learn's (they use the coupling and the studies).
"""

from fishsim.lazy import exports

__getattr__, __all__ = exports(__name__, {
    "config": ("NetConfig", "PoolConfig", "TrainConfig"),
    "loss": ("LossConfig", "LossTerms", "hydronet_loss"),
    "model_file": ("load_hydronet",),
    "unet": ("HydroNet", "HydroNetFluid"),
})
