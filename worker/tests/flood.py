"""Floods a collective port with strangers' connections for a bounded time.

Usage: flood.py HOST:PORT SECONDS CONNECTIONS_PER_SOURCE SOURCE [SOURCE ...]

From each source address it keeps up to CONNECTIONS_PER_SOURCE connections open at once,
opening new ones as the target closes old ones, of five kinds in turn: silent, junk bytes,
an oversized length prefix after the lane magic, a lane magic cut short, and a well-formed
hello for a generation the target never joins. Prints one line of key=value figures.
"""

import asyncio
import os
import resource
import struct
import sys

MAGIC = b"XFLANE01"


def varint(value):
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def far_future_hello():
    # LaneHello: generation (3), lane (4), lanes (5), nonce (6).
    body = b"\x18" + varint(1 << 60) + b"\x20\x00" + b"\x28\x01" + b"\x32\x20" + os.urandom(32)
    return MAGIC + struct.pack("<I", len(body)) + body


OPENINGS = [
    lambda: b"",
    lambda: os.urandom(64),
    lambda: MAGIC + struct.pack("<I", 0xFFFFFFF0) + b"\x00" * 16,
    lambda: MAGIC[:4],
    far_future_hello,
]


async def stranger(host, port, source, kind, deadline, figures):
    try:
        reader, writer = await asyncio.open_connection(host, port, local_addr=(source, 0))
    except OSError:
        figures["connect_failed"] += 1
        await asyncio.sleep(0.01)
        return
    figures["opened"] += 1
    try:
        opening = OPENINGS[kind % len(OPENINGS)]()
        if opening:
            writer.write(opening)
            await writer.drain()
        remaining = deadline - asyncio.get_running_loop().time()
        await asyncio.wait_for(reader.read(), timeout=max(remaining, 0.01))
        figures["closed_by_target"] += 1
    except (asyncio.TimeoutError, OSError):
        pass
    finally:
        writer.close()


async def source_loop(host, port, source, seconds, per_source, figures):
    loop = asyncio.get_running_loop()
    deadline = loop.time() + seconds
    running = set()
    kind = 0
    while loop.time() < deadline:
        while len(running) < per_source:
            task = asyncio.create_task(stranger(host, port, source, kind, deadline, figures))
            running.add(task)
            kind += 1
        done, running = await asyncio.wait(running, timeout=0.05, return_when=asyncio.FIRST_COMPLETED)
    for task in running:
        task.cancel()
    await asyncio.gather(*running, return_exceptions=True)


async def main():
    address, seconds, per_source = sys.argv[1], float(sys.argv[2]), int(sys.argv[3])
    sources = sys.argv[4:]
    host, port = address.rsplit(":", 1)
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    figures = {"opened": 0, "closed_by_target": 0, "connect_failed": 0}
    await asyncio.gather(
        *(source_loop(host, int(port), s, seconds, per_source, figures) for s in sources)
    )
    print(" ".join(f"{k}={v}" for k, v in figures.items()), flush=True)


asyncio.run(main())
