import sys, torch
import fishsim.fluid.numerical as n
tol = float(sys.argv[1])
n.IMMERSE_TOL[torch.float64] = (tol, tol)
n.IMMERSE_MAX_ITER = max(n.IMMERSE_MAX_ITER, 400)
sys.argv = ["gradcheck"] + sys.argv[2:]
from benchmarks.gradcheck import main
main()
