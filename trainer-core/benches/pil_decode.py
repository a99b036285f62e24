"""The decode benchmark's peer: the release's frame path in Python on one core.

Reads every .jpg/.jpeg/.png under DIR (sub-folders included) with PIL, takes it as a uint8 array, applies the release's
center_crop_resize (numpy bilinear at corner-aligned coordinates, truncation to uint8) to SIZE
and maps it to float32 in [-1, 1]; repeats ROUNDS times and prints `fps=N frames=M`.

usage: python3 pil_decode.py DIR [--size 256] [--rounds 4]
"""

import argparse
import io
import os
import sys
import time

import numpy as np
from PIL import Image


def center_crop_resize(im, size):
    height, width, _ = im.shape
    if height == width == size:
        return im
    side = min(height, width)
    top, left = (height - side) // 2, (width - side) // 2
    cropped = im[top:top + side, left:left + side, :]
    if side == size:
        return cropped
    coords = np.linspace(0, side - 1, size)
    low = np.floor(coords).astype(np.int32)
    high = np.clip(low + 1, 0, side - 1)
    dx = (coords - low)[None, :, None]
    dy = (coords - low)[:, None, None]
    a = cropped[low[:, None], low[None, :]]
    b = cropped[low[:, None], high[None, :]]
    c = cropped[high[:, None], low[None, :]]
    d = cropped[high[:, None], high[None, :]]
    top_row = (1 - dx) * a + dx * b
    bottom_row = (1 - dx) * c + dx * d
    return ((1 - dy) * top_row + dy * bottom_row).astype(np.uint8)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("dir")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--rounds", type=int, default=4)
    args = parser.parse_args()
    paths = sorted(
        os.path.join(root, name)
        for root, _, names in os.walk(args.dir)
        for name in names
        if name.lower().endswith((".jpg", ".jpeg", ".png"))
    )
    if not paths:
        sys.exit(f"{args.dir}: no frames")
    blobs = []
    for path in paths:
        with open(path, "rb") as file:
            blobs.append(file.read())
    def decode(blob):
        image = np.asarray(Image.open(io.BytesIO(blob)).convert("RGB"))
        frame = center_crop_resize(image, args.size)
        return 2.0 * (frame.astype(np.float32) / 255.0) - 1.0

    for blob in blobs:
        decode(blob)
    start = time.perf_counter()
    for _ in range(args.rounds):
        for blob in blobs:
            decode(blob)
    elapsed = time.perf_counter() - start
    print(f"fps={len(blobs) * args.rounds / elapsed:.1f} frames={len(blobs)}")


if __name__ == "__main__":
    main()
