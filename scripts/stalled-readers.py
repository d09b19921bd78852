#!/usr/bin/env python3
"""Opens N websocket connections to a brickcast scene that say Hello and then never read (or,
with --read, read and discard everything: idle viewers).

Used by scripts/hostile-bench to measure what such clients cost a server (memory, other
clients' latency, how long until stalled ones are cut off). Plain sockets, no dependencies: the
websocket handshake and one masked binary frame are written by hand.

    stalled-readers.py HOST PORT SCENE N SECONDS [--read]

Holds the connections for SECONDS, then prints one JSON line: how many connected and how many
were refused (idle viewers also: how many connections the server closed).
"""
import base64
import json
import os
import selectors
import socket
import sys
import time

PROTOCOL_VERSION = 1


def varint(n):
    # bincode's standard varint: < 251 in one byte, else 251 + u16 LE, 252 + u32 LE, ...
    if n < 251:
        return bytes([n])
    if n < 1 << 16:
        return bytes([251]) + n.to_bytes(2, "little")
    if n < 1 << 32:
        return bytes([252]) + n.to_bytes(4, "little")
    return bytes([253]) + n.to_bytes(8, "little")


def hello():
    name = b"stalled"
    # ClientMsg::Hello { protocol, name, token: None, resume_from: None }, variant 0.
    return varint(0) + varint(PROTOCOL_VERSION) + varint(len(name)) + name + b"\x00\x00"


def frame(payload):
    mask = os.urandom(4)
    head = bytes([0x82])
    n = len(payload)
    if n < 126:
        head += bytes([0x80 | n])
    else:
        head += bytes([0x80 | 126]) + n.to_bytes(2, "big")
    return head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


def connect(host, port, scene):
    s = socket.create_connection((host, port))
    # A small receive buffer: the server's data piles up on its side, as with a slow reader.
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
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
    s.sendall(frame(hello()))
    return s


def main():
    host, port, scene, n, seconds = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4]), float(sys.argv[5])
    read = "--read" in sys.argv[6:]
    sockets, refused = [], 0
    for _ in range(n):
        try:
            sockets.append(connect(host, port, scene))
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
