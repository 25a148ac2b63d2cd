"""The U-Net's forward (fp32, NHWC, two threads, eval mode, BatchNorm not folded) at widths 16 (the
shipped), 12, 10 and 8 on the 101 x 301 canvas, B = 1, 2 (one symmetric step) and 32 (16 fish,
symmetric): min and median of 10 calls after 3.

    python results/speed/unet_width_2026-11-30.py
"""
import time

import torch

from fishsim.fluid.hydronet.unet import UNet

torch.set_num_threads(2)
def bench(f, n=10):
    for _ in range(3): f()
    ts=[]
    for _ in range(n):
        t=time.perf_counter(); f(); ts.append(time.perf_counter()-t)
    return min(ts)*1e3, sorted(ts)[len(ts)//2]*1e3
for hid in (16, 12, 10, 8):
    net = UNet(13, 2, hid, 4).eval().to(memory_format=torch.channels_last)
    npar = sum(p.numel() for p in net.parameters())
    for B in (1, 2, 32):
        x = torch.randn(B, 13, 101, 301).contiguous(memory_format=torch.channels_last)
        with torch.no_grad():
            mn, md = bench(lambda net=net, x=x: net(x))
        print(f"hidden {hid} ({npar/1e6:.2f} M) B={B}: min {mn:.1f} ms, median {md:.1f} ms, per fish {md/B:.1f}")
