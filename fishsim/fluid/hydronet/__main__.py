"""``python -m fishsim.fluid.hydronet key=value ...``: train HydroNet (see ``train.py``)."""

from fishsim.fluid.hydronet.train import main

main()
