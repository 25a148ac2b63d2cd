"""HydroNet: the physics-constrained U-Net fluid model (paper Sec. 3.1; Wandel et al. 2021).

unet.py   network, grid-unit scaling, bounded update, ``HydroNetFluid`` (the ``FluidModel``)
loss.py   unsupervised Navier-Stokes + boundary loss (uses ``fishsim.fluid.residual``)
pool.py   randomised training scenes (obstacles, inflows, swimming fish) fed with the net's output
train.py  ``run(TrainConfig)``: training loop, checkpoints, logs, DDP; ``load_hydronet``
scales.py grid units U* = dx/h, A* = dx^2/h, P* = rho U*^2 shared by the net and the loss
config.py settings imported without torch (the CLI's help): pressure choices, ``EvalConfig``,
          ``TrainConfig``, ``NetConfig``, ``PoolConfig``
"""

from fishsim.lazy import exports

__getattr__, __all__ = exports(__name__, {
    "config": ("NetConfig", "PoolConfig", "TrainConfig"),
    "loss": ("LossConfig", "LossTerms", "hydronet_loss"),
    "pool": ("ScenePool",),
    "train": ("load_hydronet", "run"),
    "unet": ("HydroNet", "HydroNetFluid"),
})
