#!/usr/bin/env python3
"""RRDBNet (Real-ESRGAN's generator, BasicSR's architecture) in plain PyTorch, loaded with a safetensors file of
BasicSR-named weights and run on the tensor "input" of another safetensors file: the reference of the C++
RRDBNet's parity tests. The architecture (channels, growth, block count) is read off the weights' shapes.

  rrdbnet_reference.py --weights W.safetensors --input IN.safetensors --out OUT.safetensors
IN holds "input" (N x C x h x w, F32); OUT gets "output" (N x C' x 4h x 4w, F32), computed in float32 on the CPU.
Exit status 77 when a Python module it needs is missing.
"""
import argparse
import re
import sys

from f32_safetensors import MISSING_MODULE, read_safetensors, write_safetensors


def build(weights):
    import torch
    from torch import nn
    import torch.nn.functional as F

    def conv(cin, cout):
        return nn.Conv2d(cin, cout, 3, 1, 1)

    class DenseBlock(nn.Module):
        def __init__(self, feat, grow):
            super().__init__()
            for k in range(1, 6):
                setattr(self, f"conv{k}", conv(feat + (k - 1) * grow, grow if k < 5 else feat))

        def forward(self, x):
            features = [x]
            for k in range(1, 5):
                features.append(F.leaky_relu(getattr(self, f"conv{k}")(torch.cat(features, 1)), 0.2))
            return self.conv5(torch.cat(features, 1)) * 0.2 + x

    class Rrdb(nn.Module):
        def __init__(self, feat, grow):
            super().__init__()
            self.rdb1, self.rdb2, self.rdb3 = (DenseBlock(feat, grow) for _ in range(3))

        def forward(self, x):
            return self.rdb3(self.rdb2(self.rdb1(x))) * 0.2 + x

    class RrdbNet(nn.Module):
        def __init__(self, in_ch, out_ch, feat, grow, blocks):
            super().__init__()
            self.conv_first = conv(in_ch, feat)
            self.body = nn.Sequential(*(Rrdb(feat, grow) for _ in range(blocks)))
            self.conv_body = conv(feat, feat)
            self.conv_up1, self.conv_up2, self.conv_hr = conv(feat, feat), conv(feat, feat), conv(feat, feat)
            self.conv_last = conv(feat, out_ch)

        def forward(self, x):
            feat = self.conv_first(x)
            feat = feat + self.conv_body(self.body(feat))
            feat = F.leaky_relu(self.conv_up1(F.interpolate(feat, scale_factor=2, mode="nearest")), 0.2)
            feat = F.leaky_relu(self.conv_up2(F.interpolate(feat, scale_factor=2, mode="nearest")), 0.2)
            return self.conv_last(F.leaky_relu(self.conv_hr(feat), 0.2))

    feat, in_ch = weights["conv_first.weight"].shape[:2]
    grow = weights["body.0.rdb1.conv1.weight"].shape[0]
    blocks = len({m.group(1) for name in weights for m in [re.match(r"body\.(\d+)\.", name)] if m})
    out_ch = weights["conv_last.weight"].shape[0]
    model = RrdbNet(in_ch, out_ch, feat, grow, blocks)
    model.load_state_dict({name: torch.from_numpy(array) for name, array in weights.items()}, strict=True)
    return model.eval()


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", required=True)
    parser.add_argument("--input", required=True)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    try:
        import numpy  # noqa: F401
        import torch
    except ImportError as e:
        print(f"rrdbnet_reference: {e}", file=sys.stderr)
        return MISSING_MODULE
    model = build(read_safetensors(args.weights))
    x = torch.from_numpy(read_safetensors(args.input)["input"])
    with torch.no_grad():
        y = model(x)
    write_safetensors(args.out, {"output": y.numpy()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
