import sys, torch
import fishsim.coupling.layer as layer
c = float(sys.argv[1])
orig = layer.ibm_force
def scaled(qs, p, *args, **kw):
    return orig(qs, c * p, *args, **kw)
layer.ibm_force = scaled
torch.set_num_threads(1)
from fishsim.swim_study import episode
d = episode(["fluid=hydronet"], [3.0, 5.0, 7.0], 120, "cpu")["displacement_mm"]
ref = [46.925407408503375, 132.752173026506, 266.1414666301343]
print(c, [f"{x:.1f}" for x in d], [f"{x / r - 1:+.1%}" for x, r in zip(d, ref)], flush=True)
