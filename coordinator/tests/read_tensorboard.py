"""Reads a job's TensorBoard runs with TensorBoard's own EventAccumulator (no TensorFlow) and
prints what it found as JSON: per run, the scalars (tag -> [[step, value], ...]), the images
(tag -> [{step, width, height, png}]) with `png` true when the bytes are a PNG of that size,
and the text summaries (tag -> [text, ...])."""

import json
import os
import struct
import sys

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

EVERYTHING = {"scalars": 0, "images": 0, "tensors": 0}


def png_size(data):
    if data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", data[16:24])


def read_run(path):
    accumulator = EventAccumulator(path, size_guidance=EVERYTHING)
    accumulator.Reload()
    tags = accumulator.Tags()
    scalars = {
        tag: [[event.step, event.value] for event in accumulator.Scalars(tag)]
        for tag in tags["scalars"]
    }
    images = {}
    for tag in tags["images"]:
        images[tag] = [
            {
                "step": event.step,
                "width": event.width,
                "height": event.height,
                "png": png_size(event.encoded_image_string) == (event.width, event.height),
            }
            for event in accumulator.Images(tag)
        ]
    texts = {
        tag: [
            b"".join(event.tensor_proto.string_val).decode("utf-8")
            for event in accumulator.Tensors(tag)
        ]
        for tag in tags["tensors"]
    }
    return {"scalars": scalars, "images": images, "texts": texts}


def main():
    logdir = sys.argv[1]
    runs = {
        name: read_run(os.path.join(logdir, name))
        for name in sorted(os.listdir(logdir))
        if os.path.isdir(os.path.join(logdir, name))
    }
    json.dump(runs, sys.stdout)


if __name__ == "__main__":
    main()
