#!/usr/bin/env python3
"""SSIM map of the original 3D Gaussian Splatting code (utils/loss_utils.py), for tests/losses_test.cpp.

Reads two raw float64 HxWxC images (row-major), writes the per-pixel SSIM map (HxWxC float64).
The functions below are the 3DGS ones, verbatim except that the window is built in float64 so that
the comparison is not limited by float32 rounding.
"""
import argparse
import sys
from math import exp


def gaussian(window_size, sigma):
    import torch
    gauss = torch.tensor([exp(-(x - window_size // 2) ** 2 / float(2 * sigma ** 2))
                          for x in range(window_size)], dtype=torch.float64)
    return gauss / gauss.sum()


def create_window(window_size, channel):
    _1D_window = gaussian(window_size, 1.5).unsqueeze(1)
    _2D_window = _1D_window.mm(_1D_window.t()).unsqueeze(0).unsqueeze(0)
    return _2D_window.expand(channel, 1, window_size, window_size).contiguous()


def ssim_map(img1, img2, window_size=11):
    import torch.nn.functional as F
    channel = img1.size(-3)
    window = create_window(window_size, channel)
    mu1 = F.conv2d(img1, window, padding=window_size // 2, groups=channel)
    mu2 = F.conv2d(img2, window, padding=window_size // 2, groups=channel)
    mu1_sq = mu1.pow(2)
    mu2_sq = mu2.pow(2)
    mu1_mu2 = mu1 * mu2
    sigma1_sq = F.conv2d(img1 * img1, window, padding=window_size // 2, groups=channel) - mu1_sq
    sigma2_sq = F.conv2d(img2 * img2, window, padding=window_size // 2, groups=channel) - mu2_sq
    sigma12 = F.conv2d(img1 * img2, window, padding=window_size // 2, groups=channel) - mu1_mu2
    C1 = 0.01 ** 2
    C2 = 0.03 ** 2
    return ((2 * mu1_mu2 + C1) * (2 * sigma12 + C2)) / (
        (mu1_sq + mu2_sq + C1) * (sigma1_sq + sigma2_sq + C2))


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--pred", required=True)
    parser.add_argument("--gt", required=True)
    parser.add_argument("--shape", required=True, type=int, nargs=3, metavar=("H", "W", "C"))
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    try:
        import numpy as np
        import torch
    except ImportError as error:
        sys.exit(f"ssim_reference.py: {error}; scripts/setup.sh installs torch and numpy")
    load = lambda path: torch.from_numpy(
        np.fromfile(path, dtype="<f8").reshape(args.shape)).permute(2, 0, 1)[None]
    result = ssim_map(load(args.pred), load(args.gt))[0].permute(1, 2, 0)
    result.contiguous().numpy().astype("<f8").tofile(args.out)


if __name__ == "__main__":
    main()
