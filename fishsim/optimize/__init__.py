"""Optimising a swimmer: parameters and objectives (problem), optimisers (methods), the run
(fishsim.commands.optimize)."""
