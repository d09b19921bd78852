#!/usr/bin/env python3
"""What one undo (or redo) of a large step costs a server: one user fills two 256³ boxes in one
edit (33.5 M voxels), waits for the ack, then undoes and redoes it ROUNDS times, each time
waiting for the reply (`Undone`) before the next. Prints each reply's latency and the scene
owner's time per phase (`brickcast_owner_seconds_total`) spent over the undos and redos.
For scripts/fair-share-bench's ATTACK=boxes runs (BENCHMARKS.md, "Fair share").

    undo-cost.py HOST PORT SCENE [ROUNDS=6]

PROTOCOL=N speaks an older protocol (hostile-client.py's).
"""
import importlib.util
import json
import os
import re
import sys
import time
import urllib.request

spec = importlib.util.spec_from_file_location(
    "hostile", os.path.join(os.path.dirname(os.path.abspath(__file__)), "hostile-client.py"))
hostile = importlib.util.module_from_spec(spec)
spec.loader.exec_module(hostile)

ACK, UNDONE = hostile.ACK, 9  # ServerMsg variants


def phases(host, port):
    text = urllib.request.urlopen(f"http://{host}:{port}/metrics").read().decode()
    return {m.group(1): float(m.group(2))
            for m in re.finditer(r'brickcast_owner_seconds_total\{phase="(\w+)"\} ([\d.e+-]+)', text)}


def main():
    host, port, scene = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    rounds = int(sys.argv[4]) if len(sys.argv) > 4 else 6
    s = hostile.connect(host, port, scene, user=0x30000, rcvbuf=1 << 20)
    stream = hostile.frames(s)
    two = [([0, 0, 0], [255, 255, 255]), ([256, 0, 256], [511, 255, 511])]
    t = time.time()
    s.sendall(hostile.frame(hostile.box_edit(1, two, 0x1234)))
    hostile.until(stream, ACK, 1)
    edit_s = time.time() - t
    before = phases(host, port)
    latencies = []
    for i in range(2 * rounds):
        seq = 2 + i
        t = time.time()
        s.sendall(hostile.frame(hostile.undo(seq) if i % 2 == 0 else hostile.redo(seq)))
        hostile.until(stream, UNDONE, seq)
        latencies.append(round((time.time() - t) * 1000, 1))
    after = phases(host, port)
    spent = {k: round((after[k] - before[k]) / (2 * rounds) * 1000, 1) for k in after if k != "wait"}
    print(json.dumps({"edit_s": round(edit_s, 2), "reply_ms": latencies,
                      "owner_ms_per_undo": spent}))


if __name__ == "__main__":
    main()
