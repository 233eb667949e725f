#!/usr/bin/env python3
"""LPIPS-VGG distances of image pairs from PyPI's `lpips` (0.1.4: LPIPS(net='vgg', version='0.1'), called with
normalize=True) on torchvision's vgg16(weights=None) loaded with the set-up's converted weights
(scripts/lpips_weights.py) - the reference of the real-weights parity tests.

  lpips_real_reference.py --weights FILE.safetensors --pairs PAIRS.json --out DISTANCES.json
PAIRS.json: [[image_a, image_b], ...] (PNG or JPEG files). DISTANCES.json: [d, ...] in the same order.
Exit status 77 when a Python module it needs is missing.
"""
import argparse
import json
import sys

from f32_safetensors import MISSING_MODULE, read_safetensors


def reference_model(weights_path):
    import lpips
    import torch
    import torchvision
    tensors = {name: torch.from_numpy(array) for name, array in read_safetensors(weights_path).items()}
    vgg = torchvision.models.vgg16(weights=None)
    features = {name[len("features."):]: t for name, t in tensors.items() if name.startswith("features.")}
    vgg.features.load_state_dict(features, strict=True)
    # pnet_rand: no torchvision download; the trunk comes from `vgg` below. The heads are lpips' own v0.1 file.
    model = lpips.LPIPS(net="vgg", version="0.1", pretrained=True, pnet_rand=True, verbose=False)
    for part in (model.net.slice1, model.net.slice2, model.net.slice3, model.net.slice4, model.net.slice5):
        for name, module in part._modules.items():
            module.load_state_dict(vgg.features[int(name)].state_dict())
    state = model.state_dict()
    for tap in range(5):
        key = f"lin{tap}.model.1.weight"
        assert torch.equal(state[key], tensors[key]), f"{key} of {weights_path} differs from lpips' v0.1 heads"
    return model.eval()


def read_rgb(path):
    import numpy as np
    import torch
    from PIL import Image
    image = np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0
    return torch.from_numpy(image).permute(2, 0, 1)[None]


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--weights", required=True)
    parser.add_argument("--pairs", required=True)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    try:
        import torch
        model = reference_model(args.weights)
    except ImportError as e:
        print(f"missing Python module: {e}", file=sys.stderr)
        return MISSING_MODULE
    with open(args.pairs) as f:
        pairs = json.load(f)
    distances = []
    with torch.no_grad():
        for a, b in pairs:
            distances.append(model(read_rgb(a), read_rgb(b), normalize=True).item())
    with open(args.out, "w") as f:
        json.dump(distances, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
