"""Learning HydroNet: the randomised training scenes (``pool``), the training loop with its
checkpoints and logs (``train``, the CLI's ``train-hydronet``), the evaluation against the
numerical solver (``evaluate``, ``validate suite=hydronet``), the frequency-study check run during
training (``swim_check``) and the shipping of a model with its metadata (``ship``). It sits above
the fluids, the coupling and the studies it draws on; the network itself and its FluidModel are
fishsim.fluid.hydronet's."""
