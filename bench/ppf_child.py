"""Child process of bench/peers.py's PPF peer: OpenCV's point-pair-feature detector (cv2.ppf_match_3d, in
opencv-contrib), which cannot share a process with gscan's opencv-python-headless (both are the module cv2).

Started with opencv-contrib's folder first on PYTHONPATH; reads requests from stdin and writes answers to stdout,
each a length-prefixed pickle. A request (key, model [N x 6] float32 | None, scene [M x 6] float32, top) trains
the detector on the model (points and unit normals, m) unless `key` names the one trained last, matches the scene
and answers ([(T_scene_model [4 x 4], votes)] of the `top` poses with most votes, CPU seconds). Parameters are
OpenCV's sample's: model sampling 0.05 and distance step 0.05 of the model's diameter, every 5th scene point after
sampling at 0.05. The caller refines the poses (OpenCV's ICP diverges on whole scenes: residuals of 1e10 m).
"""
from __future__ import annotations

import pickle
import struct
import sys
import time

import cv2
import numpy as np


def read(stream):
    """The next length-prefixed pickle of a binary stream, or None at its end."""
    head = stream.read(8)
    if len(head) < 8:
        return None
    return pickle.loads(stream.read(struct.unpack("<Q", head)[0]))


def write(stream, obj) -> None:
    """obj to a binary stream as a length-prefixed pickle."""
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(struct.pack("<Q", len(data)) + data)
    stream.flush()


def main() -> None:
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    trained: dict[str, tuple] = {}
    while (req := read(inp)) is not None:
        key, model, scene, top = req
        t0 = time.process_time()
        if key not in trained:
            detector = cv2.ppf_match_3d.PPF3DDetector(0.05, 0.05)  # opencv-contrib's module
            detector.trainModel(model)
            trained = {key: (detector, model)}  # one model at a time: the callers go model by model
        detector, model = trained[key]
        results = detector.match(scene, 1.0 / 5.0, 0.05)
        results = sorted(results, key=lambda r: -r.numVotes)[:top]
        poses = [(np.asarray(r.pose, np.float64), int(r.numVotes)) for r in results]
        write(out, (poses, time.process_time() - t0))


if __name__ == "__main__":
    main()
