"""How far the shipped U-Net looks: |d p_out(50, 150) / d input| over a 101 x 301 canvas (the paper's tank's
vertex grid), random input, the trunk alone in eval mode; the extent of non-zero sensitivity and the share within
+-r columns of the output's.

    python results/hydronet_training/2026-11-30c/receptive_field.py > receptive_field.txt
"""
import torch

from fishsim.fluid.hydronet.model_file import load_hydronet

torch.set_num_threads(2)
torch.manual_seed(0)
net = load_hydronet("fishsim/assets/hydronet.pt").unet.float().eval()
for p in net.parameters():
    p.requires_grad_(False)
H, W = 101, 301
x = torch.randn(1, net.inc[0].in_channels, H, W, requires_grad=True)
out = net(x)
out[0, 1, 50, 150].backward()
g = x.grad.abs().sum(dim=(0, 1))
cols = (g.sum(0) > 0).nonzero().flatten(); rows = (g.sum(1) > 0).nonzero().flatten()
print("receptive field of the pressure output at (50,150): columns", cols.min().item(), "-", cols.max().item(), "rows", rows.min().item(), "-", rows.max().item())
c = g.sum(0); c = c / c.sum()
cs = c.numpy()
for r in (16, 32, 64, 96, 128):
    print(f"share of |d p / d input| within +-{r} columns: {cs[max(0,150-r):150+r+1].sum():.3f}")
