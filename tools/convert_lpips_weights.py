#!/usr/bin/env python3
"""Convert the authors' LPIPS weight files to the safetensors layout trainer-core reads.

    python3 tools/convert_lpips_weights.py vgg16_weights.h5 lpips_lin.h5 lpips-vgg16.safetensors

Input layout (as the authors' JAX LPIPS reads it):
  vgg16_weights.h5: groups conv{b}_{l} (b 1..5) with datasets `weight` (3x3xCinxCout, HWIO) and
                    `bias` (Cout)
  lpips_lin.h5:     datasets lin0..lin4 of shape 1x1xCx1
Output names: vgg.conv{b}_{l}.weight, vgg.conv{b}_{l}.bias, lin.lin{i} (float32, same shapes).
Needs: pip install h5py numpy safetensors
"""
import sys

import h5py
import numpy as np
from safetensors.numpy import save_file

DEPTHS = [2, 2, 3, 3, 3]


def dataset(group, name, path):
    if name not in group:
        sys.exit(f"{path}: missing `{name}` (found: {sorted(group.keys())})")
    return np.asarray(group[name], dtype=np.float32)


def main(argv):
    if len(argv) != 4:
        sys.exit(__doc__)
    vgg_path, lin_path, out_path = argv[1:]
    tensors = {}
    with h5py.File(vgg_path, "r") as vgg:
        for block, depth in enumerate(DEPTHS, start=1):
            for layer in range(1, depth + 1):
                name = f"conv{block}_{layer}"
                if name not in vgg:
                    sys.exit(f"{vgg_path}: missing group `{name}`")
                tensors[f"vgg.{name}.weight"] = dataset(vgg[name], "weight", vgg_path)
                tensors[f"vgg.{name}.bias"] = dataset(vgg[name], "bias", vgg_path)
    with h5py.File(lin_path, "r") as lin:
        for i in range(5):
            tensors[f"lin.lin{i}"] = dataset(lin, f"lin{i}", lin_path)
    save_file(tensors, out_path)
    print(f"wrote {out_path}: {len(tensors)} tensors")


if __name__ == "__main__":
    main(sys.argv)
