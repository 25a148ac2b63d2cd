"""A trained HydroNet from its file (best.pt, ckpt.pt or the shipped model): ``load_hydronet``,
with one-line errors for a missing, unreadable, foreign or misshapen file."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from fishsim.errors import ConfigError, InputFileError
from fishsim.fluid.hydronet.config import NetConfig
from fishsim.fluid.hydronet.trained_range import stored_range
from fishsim.fluid.hydronet.unet import HydroNet


def load_hydronet(path: str | Path, device="cpu") -> HydroNet:
    """A trained HydroNet (eval mode) from best.pt or ckpt.pt, with its ``training_range`` (None if
    unknown; ``trained_range.check_fluid``); wrap it in ``HydroNetFluid``.

    Raises InputFileError (one line, how to fix) for a missing, unreadable or foreign file, and
    ConfigError naming the first tensor that does not fit the file's own network config."""
    path = Path(path)
    hint = "train one with `fishsim train-hydronet` or pass fluid.model_file=PATH to a best.pt"
    sd = load_file(path, "model", hint)
    try:
        model = HydroNet(NetConfig(**sd["net"]))
    except (KeyError, TypeError) as err:
        raise InputFileError(f"{path} is not a readable HydroNet model (no valid network config: "
                             f"{type(err).__name__}); {hint}") from None
    load_weights(model, sd, path)
    model.training_range = stored_range(sd, path)     # checked against a run's fluid: trained_range.py
    return model.to(device).eval()


def load_file(path: Path, what: str, hint: str = "") -> dict:
    """torch.load of a fishsim checkpoint or model (on the CPU), InputFileError (one line, ending
    in ``hint``) if it is missing or not one."""
    end = f"; {hint}" if hint else ""
    if not path.is_file():
        raise InputFileError(f"HydroNet {what} file {path} not found{end}")
    try:
        data = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # noqa: BLE001 - any failure here means the file is not ours
        raise InputFileError(f"{path} is not a readable HydroNet {what} ({type(err).__name__}){end}") from None
    if not isinstance(data, dict) or "model" not in data:
        raise InputFileError(f"{path} is not a readable HydroNet {what} (no 'model' weights in it){end}")
    return data


def load_weights(model: nn.Module, data: dict, path: Path) -> None:
    """Load data["model"] into ``model``; a network of another shape is a one-line error naming the
    first tensor that differs and the file's network config."""
    own, theirs = model.state_dict(), data["model"]
    for name, tensor in own.items():
        other = theirs.get(name)
        if other is None or tuple(other.shape) != tuple(tensor.shape):
            net = (data.get("config") or {}).get("net")
            got = "missing" if other is None else f"{list(other.shape)}"
            raise ConfigError(f"the weights in {path} do not fit this network: tensor '{name}' is {got} there and "
                              f"{list(tensor.shape)} here" + (f"; the file's network is net={net}" if net else "")
                              + " (set net.* to match, or train from scratch)")
    model.load_state_dict(theirs)
