#!/usr/bin/env python3
"""Hostile brickcast clients, for scripts/hostile-bench: what they cost a server (memory, other
clients' latency, how long until it cuts them off). Plain sockets, no dependencies: the websocket
handshake, the frames and the bincode of the few messages used are written by hand.

    hostile-client.py crowd HOST PORT SCENE N SECONDS [--read] [--sources K]
        N connections that say Hello and then never read (stalled readers), or with --read read
        and discard everything (idle viewers); with --sources K, from K loopback addresses.
    hostile-client.py ping|camera|huge HOST PORT SCENE SECONDS
        One connection that never reads and keeps sending Pings, Camera updates, or Edit
        messages of 4,096 spheres of radius 64.
    hostile-client.py replies HOST PORT SCENE N SECONDS
        N connections that never read and keep sending requests the server answers: refused
        presence (a cursor outside the scene), Undo with nothing to undo, Edit messages refused
        for their work (64 spheres of radius 64) and Pings, in turn.
    hostile-client.py brushes HOST PORT SCENE N SECONDS
        N connections, each at its own edit budget with allowed-size brushes (15 spheres of
        radius 64 per message, two messages a second), reading their replies.
    hostile-client.py boxes HOST PORT SCENE N SECONDS
        N users (ids of their own), each filling two 256³ boxes in one message (33.5 M voxels,
        the most one edit may ask for), then undoing and redoing that step in turn, one request
        a second each, reading and discarding every reply.
    hostile-client.py ids HOST PORT SCENE N SECONDS RADIUS
        N connections one after another over SECONDS, each with a user id of its own, each
        painting one sphere of RADIUS: N users' undo history in one scene.
    hostile-client.py http HOST PORT PATH N SECONDS
        N threads each asking for PATH over HTTP/1.1 (a connection per request, from
        127.0.0.2), again as soon as answered, for SECONDS: 200 of them on a scene's
        thumbnail (kept stale by an editor) against 200 on "/".

Holds the connections for SECONDS, then prints one JSON line: how many connected and how many
were refused (idle viewers also: how many connections the server closed).
"""
import base64
import json
import os
import selectors
import socket
import struct
import sys
import time

# The protocol spoken; PROTOCOL=N in the environment for an older server.
PROTOCOL_VERSION = int(os.environ.get("PROTOCOL", "3"))


ACK = 5  # ServerMsg::Ack's variant


def varint(n):
    # bincode's standard varint: < 251 in one byte, else 251 + u16 LE, 252 + u32 LE, ...
    if n < 251:
        return bytes([n])
    if n < 1 << 16:
        return bytes([251]) + n.to_bytes(2, "little")
    if n < 1 << 32:
        return bytes([252]) + n.to_bytes(4, "little")
    return bytes([253]) + n.to_bytes(8, "little")


def hello(user=0):
    name = b"stalled"
    # ClientMsg::Hello { protocol, name, token: None, resume_from: None, user }, variant 0.
    return varint(0) + varint(PROTOCOL_VERSION) + varint(len(name)) + name + b"\x00\x00" + varint(user)


def frame(payload):
    mask = os.urandom(4)
    head = bytes([0x82])
    n = len(payload)
    if n < 126:
        head += bytes([0x80 | n])
    elif n < 1 << 16:
        head += bytes([0x80 | 126]) + n.to_bytes(2, "big")
    else:
        head += bytes([0x80 | 127]) + n.to_bytes(8, "big")
    return head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


def connect(host, port, scene, source=None, user=0, rcvbuf=4096):
    # `source`: another loopback address to come from (the server limits connections per
    # address, and the well-behaved probe must not count against the attackers' allowance).
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    # A small receive buffer (set before connecting, so the window is small from the start):
    # the server's data piles up on its side, as with a slow reader.
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    if source:
        s.bind((source, 0))
    s.connect((host, port))
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall(
        (
            f"GET /scenes/{scene}/ws HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    reply = b""
    while b"\r\n\r\n" not in reply:
        chunk = s.recv(1)
        if not chunk:
            raise ConnectionError("closed during the handshake")
        reply += chunk
    if not reply.startswith(b"HTTP/1.1 101"):
        raise ConnectionError(reply.split(b"\r\n")[0].decode())
    s.sendall(frame(hello(user)))
    return s


def f32s(values):
    return b"".join(struct.pack("<f", v) for v in values)


def ping(nonce):
    # ClientMsg::Ping { nonce }, variant 4.
    return varint(4) + varint(nonce)


def camera(eye):
    # ClientMsg::Camera { eye, forward }, variant 2: six f32.
    return varint(2) + f32s(eye) + f32s([0.0, 0.0, 1.0])


def huge_edit(client_seq, n):
    # ClientMsg::Edit { client_seq, ops }, variant 1, with n ops EditOp::Sphere (variant 3):
    # centre [f32; 3], radius f32, mode BrushMode::Fill (0), colour u16.
    sphere = varint(3) + f32s([256.0, 128.0, 256.0]) + f32s([64.0]) + varint(0) + varint(0x07E0)
    return varint(1) + varint(client_seq) + varint(n) + sphere * n


def sphere_edit(client_seq, centre, radius, colour):
    # ClientMsg::Edit with one EditOp::Sphere (Fill).
    sphere = varint(3) + f32s(centre) + f32s([radius]) + varint(0) + varint(colour)
    return varint(1) + varint(client_seq) + varint(1) + sphere


def frames(sock):
    """Yields the payloads of the server's websocket frames (binary, unmasked)."""
    buf = b""
    while True:
        while True:
            if len(buf) >= 2:
                n, at = buf[1] & 0x7F, 2
                if n == 126:
                    n, at = int.from_bytes(buf[2:4], "big"), 4
                elif n == 127:
                    n, at = int.from_bytes(buf[2:10], "big"), 10
                if len(buf) >= at + n:
                    yield buf[at:at + n]
                    buf = buf[at + n:]
                    continue
            break
        chunk = sock.recv(1 << 20)
        if not chunk:
            return
        buf += chunk


def until(stream, variant, client_seq):
    for payload in stream:
        if payload and payload[0] == variant and payload[1:2] == varint(client_seq)[:1]:
            return
    raise ConnectionError("closed before the reply")


def ids(host, port, scene, n, seconds, radius):
    """N connections one after another over SECONDS, each with a user id of its own (as any
    client may choose without --auth), each painting one sphere of RADIUS somewhere in the
    scene's first 512 voxels: every one leaves an undo step in the scene's history."""
    import random
    rng = random.Random(28)
    done, refused = 0, 0
    start = time.time()
    for i in range(n):
        try:
            s = connect(host, port, scene, source="127.0.0.2", user=0x10000 + i, rcvbuf=1 << 20)
            centre = [rng.uniform(radius, 512 - radius), rng.uniform(radius, 64.0), rng.uniform(radius, 512 - radius)]
            s.sendall(frame(sphere_edit(1, centre, float(radius), rng.randrange(1, 1 << 16))))
            # Read until the edit's ack (in among the sync), then leave.
            s.settimeout(10)
            until(frames(s), ACK, 1)
            s.close()
            done += 1
        except (ConnectionError, OSError):
            refused += 1
        behind = start + seconds * (i + 1) / n - time.time()
        if behind > 0:
            time.sleep(behind)
    print(json.dumps({"attack": "ids", "connections": done, "refused": refused}))


def http_flood(host, port, path, n, seconds):
    """N threads asking for PATH one request after another for SECONDS; prints the answers
    counted by status."""
    import threading
    counts, lock = {}, threading.Lock()
    end = time.time() + seconds
    request = f"GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n".encode()

    def one():
        while time.time() < end:
            status = "error"
            try:
                s = socket.create_connection((host, port), timeout=60, source_address=("127.0.0.2", 0))
                s.sendall(request)
                got = b""
                while True:
                    chunk = s.recv(1 << 16)
                    if not chunk:
                        break
                    got += chunk
                s.close()
                status = got.split(b" ", 2)[1].decode() if got.startswith(b"HTTP/") else "short"
            except OSError:
                time.sleep(0.01)
            with lock:
                counts[status] = counts.get(status, 0) + 1

    threads = [threading.Thread(target=one) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    print(json.dumps({"attack": "http", "path": path, "answers": counts}))


def paced(conns, seconds, interval, first_at, message):
    """Every INTERVAL s from FIRST_AT, sends each connection message(seq) (seq counts rounds
    times connections), reading and discarding every reply meanwhile. Returns messages sent."""
    sel = selectors.DefaultSelector()
    for s in conns:
        s.setblocking(False)
        sel.register(s, selectors.EVENT_READ)
    sent, seq, end = 0, 0, time.time() + seconds
    next_at = first_at
    while time.time() < end:
        if time.time() >= next_at:
            next_at += interval
            for s in conns:
                seq += 1
                try:
                    s.setblocking(True)
                    s.sendall(frame(message(seq)))
                    s.setblocking(False)
                    sent += 1
                except OSError:
                    pass
        for key, _ in sel.select(timeout=max(0.0, min(0.05, next_at - time.time()))):
            try:
                if not key.fileobj.recv(1 << 20):
                    sel.unregister(key.fileobj)
            except BlockingIOError:
                pass
            except OSError:
                sel.unregister(key.fileobj)
    return sent


def brushes(host, port, scene, n, seconds):
    """N connections, each at its own edit budget: a message of 15 spheres of radius 64
    (31.5 M voxels of work, just under --max-work-per-edit) every half second (63 M/s, just
    under --max-work-per-second), reading and discarding every reply."""
    import random
    rng = random.Random(8)
    conns = []
    for _ in range(n):
        try:
            conns.append(connect(host, port, scene, source="127.0.0.2"))
        except (ConnectionError, OSError):
            pass

    def message(seq):
        ops = b"".join(
            varint(3) + f32s([rng.uniform(64, 448), rng.uniform(0, 64), rng.uniform(64, 448)])
            + f32s([64.0]) + varint(rng.randrange(2)) + varint(rng.randrange(1, 1 << 16))
            for _ in range(15)
        )
        return varint(1) + varint(seq) + varint(15) + ops

    sent = paced(conns, seconds, 0.5, time.time(), message)
    print(json.dumps({"attack": "brushes", "connections": len(conns), "messages_sent": sent}))


def box_edit(client_seq, boxes, colour):
    # ClientMsg::Edit with EditOp::Box (variant 4) ops: min, max ([u32; 3] each), mode Fill (0),
    # colour u16.
    ops = b"".join(
        varint(4) + b"".join(varint(v) for v in lo) + b"".join(varint(v) for v in hi)
        + varint(0) + varint(colour)
        for lo, hi in boxes
    )
    return varint(1) + varint(client_seq) + varint(len(boxes)) + ops


def redo(client_seq):
    # ClientMsg::Redo { client_seq }, variant 6.
    return varint(6) + varint(client_seq)


def boxes(host, port, scene, n, seconds):
    """N users, each with a step of two 256³ boxes, undoing and redoing it once a second."""
    two = [([0, 0, 0], [255, 255, 255]), ([256, 0, 256], [511, 255, 511])]
    conns = []
    for i in range(n):
        try:
            s = connect(host, port, scene, source="127.0.0.2", user=0x20000 + i)
            s.sendall(frame(box_edit(1, two, 0x1000 + 0x0101 * i)))
            conns.append(s)
        except (ConnectionError, OSError):
            pass
    # Each connection's requests alternate undo, redo (client_seq from 2: the edit was 1).
    rounds = max(1, len(conns))
    sent = paced(conns, seconds, 1.0, time.time() + 1.0,
                 lambda seq: undo(seq + 1) if ((seq - 1) // rounds) % 2 == 0 else redo(seq + 1))
    print(json.dumps({"attack": "boxes", "connections": len(conns), "undos_and_redos_sent": sent}))


def refused_presence():
    # ClientMsg::Presence { view: None, cursor: Some(Cursor { voxel: [u32; 3], radius }) },
    # variant 7, with the cursor far outside any scene.
    return varint(7) + b"\x00\x01" + varint(4_000_000_000) * 3 + f32s([1.0])


def undo(client_seq):
    # ClientMsg::Undo { client_seq }, variant 5.
    return varint(5) + varint(client_seq)


def replies(host, port, scene, n, seconds):
    """N connections that never read, each sending requests the server must answer."""
    conns, refused = [], 0
    for _ in range(n):
        try:
            s = connect(host, port, scene, source="127.0.0.2")
            s.setblocking(False)
            conns.append([s, b""])
        except (ConnectionError, OSError):
            refused += 1
    # One chunk of frames, built once and sent again and again (masking in Python is slow, and
    # the attack is only as good as its sending rate).
    kinds = [refused_presence(), None, None, ping(1)]
    chunk = b"".join(
        frame((kinds[k % 4] if k % 4 in (0, 3) else undo(k) if k % 4 == 1 else huge_edit(k, 64)))
        for k in range(200)
    )
    sent, end = 0, time.time() + seconds
    while time.time() < end and conns:
        progressed = False
        for c in list(conns):
            if not c[1]:
                c[1] = chunk
                sent += 200
            try:
                m = c[0].send(c[1])
                c[1] = c[1][m:]
                progressed = progressed or m > 0
            except BlockingIOError:
                pass
            except OSError:
                conns.remove(c)
        if not progressed:
            time.sleep(0.002)
    print(json.dumps({"attack": "replies", "connected": n - refused, "refused": refused,
                      "messages_offered": sent, "open_at_end": len(conns)}))


def attack(host, port, scene, kind, seconds):
    """One connection that keeps sending `kind` messages for `seconds` and never reads."""
    s = connect(host, port, scene)
    s.setblocking(False)
    sent, end, i = 0, time.time() + seconds, 0
    pending = b""
    while time.time() < end:
        if not pending:
            i += 1
            if kind == "ping":
                pending = b"".join(frame(ping(i + k)) for k in range(100))
            elif kind == "camera":
                pending = b"".join(frame(camera([float((i + k) % 500), 300.0, 5.0])) for k in range(100))
            elif kind == "huge":
                pending = frame(huge_edit(i, 4096))
            sent += 1 if kind == "huge" else 100
        try:
            n = s.send(pending)
            pending = pending[n:]
        except BlockingIOError:
            time.sleep(0.001)
        except OSError:
            break
    print(json.dumps({"attack": kind, "messages_sent": sent}))


def main():
    if sys.argv[1] == "replies":
        host, port, scene, n, seconds = sys.argv[2], int(sys.argv[3]), sys.argv[4], int(sys.argv[5]), float(sys.argv[6])
        replies(host, port, scene, n, seconds)
        return
    if sys.argv[1] == "brushes":
        host, port, scene, n, seconds = sys.argv[2], int(sys.argv[3]), sys.argv[4], int(sys.argv[5]), float(sys.argv[6])
        brushes(host, port, scene, n, seconds)
        return
    if sys.argv[1] == "boxes":
        host, port, scene, n, seconds = sys.argv[2], int(sys.argv[3]), sys.argv[4], int(sys.argv[5]), float(sys.argv[6])
        boxes(host, port, scene, n, seconds)
        return
    if sys.argv[1] == "ids":
        host, port, scene, n, seconds, radius = sys.argv[2], int(sys.argv[3]), sys.argv[4], int(sys.argv[5]), float(sys.argv[6]), float(sys.argv[7])
        ids(host, port, scene, n, seconds, radius)
        return
    if sys.argv[1] == "http":
        host, port, path, n, seconds = sys.argv[2], int(sys.argv[3]), sys.argv[4], int(sys.argv[5]), float(sys.argv[6])
        http_flood(host, port, path, n, seconds)
        return
    if sys.argv[1] in ("ping", "camera", "huge"):
        kind, host, port, scene, seconds = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4], float(sys.argv[5])
        attack(host, port, scene, kind, seconds)
        return
    sys.argv = sys.argv[:1] + sys.argv[2:] if sys.argv[1] == "crowd" else sys.argv
    crowd()


def crowd():
    host, port, scene, n, seconds = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4]), float(sys.argv[5])
    read = "--read" in sys.argv[6:]
    # --sources K: the connections come from 127.0.0.2 ... 127.0.0.(K+1) in turn, K addresses
    # under the per-address limit each.
    k = int(sys.argv[sys.argv.index("--sources") + 1]) if "--sources" in sys.argv else 0
    sockets, refused = [], 0
    for i in range(n):
        try:
            sockets.append(connect(host, port, scene, source=f"127.0.0.{2 + i % k}" if k else None))
        except (ConnectionError, OSError):
            refused += 1
    if read:
        # Idle viewers: take everything the server sends, look at none of it.
        sel = selectors.DefaultSelector()
        for s in sockets:
            s.setblocking(False)
            sel.register(s, selectors.EVENT_READ)
        ended = 0
        deadline = time.time() + seconds
        while time.time() < deadline:
            for key, _ in sel.select(timeout=0.2):
                try:
                    if not key.fileobj.recv(1 << 20):
                        sel.unregister(key.fileobj)
                        ended += 1
                except BlockingIOError:
                    pass
                except OSError:
                    sel.unregister(key.fileobj)
                    ended += 1
        print(json.dumps({"connected": len(sockets), "refused": refused, "closed_by_server": ended}))
        return
    time.sleep(seconds)
    # Whether the server cut them off is read from its /metrics (brickcast_stalled_disconnects_total):
    # a server that closes a socket whose peer's window is zero cannot get its FIN through either.
    print(json.dumps({"connected": len(sockets), "refused": refused}))


if __name__ == "__main__":
    main()
