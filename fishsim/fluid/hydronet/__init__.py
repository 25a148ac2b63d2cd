"""HydroNet: the physics-constrained U-Net fluid model (paper Sec. 3.1; Wandel et al. 2021).

unet.py   network, grid-unit scaling, bounded update, ``HydroNetFluid`` (the ``FluidModel``)
loss.py   unsupervised Navier-Stokes + boundary loss (uses ``fishsim.fluid.residual``)
pool.py   randomised training scenes (obstacles, inflows, swimming fish) fed with the net's output
train.py  ``run(TrainConfig)``: training loop, checkpoints, logs, DDP; ``load_hydronet``
scales.py grid units U* = dx/h, A* = dx^2/h, P* = rho U*^2 shared by the net and the loss
"""

from fishsim.fluid.hydronet.loss import LossConfig, LossTerms, hydronet_loss
from fishsim.fluid.hydronet.pool import PoolConfig, ScenePool
from fishsim.fluid.hydronet.train import TrainConfig, load_hydronet, run
from fishsim.fluid.hydronet.unet import HydroNet, HydroNetFluid, NetConfig

__all__ = [
    "HydroNet",
    "HydroNetFluid",
    "LossConfig",
    "LossTerms",
    "NetConfig",
    "PoolConfig",
    "ScenePool",
    "TrainConfig",
    "hydronet_loss",
    "load_hydronet",
    "run",
]
