"""A datagram's round trip on loopback between two processes, with nothing else in it: the floor under the live
service's pen (two wake-ups: the server's and the client's), and what socket options and a spinning client change.

    .venv/bin/python benchmarks/bench_loopback.py [--seconds 3] [--hz 360] [--csharp]

An echo process (blocking receive, send back) and this client (send a 104-byte datagram at --hz, wait for its echo),
one variant after another, each twice in turn (ABAB...), under the machine's load as it is:

- `block`: the client blocks in its receive (one wake-up for the echo, as the live clients wait);
- `spin`: the client polls its non-blocking socket for the echo for at most 0.5 ms, then blocks;
- `echo_spin`: the echo process polls for the next datagram for at most 3 ms after each echo, then blocks (the pen
  process spinning after each pen: the next pen comes 2.8 ms later at 360 Hz, so a shorter spin catches none);
- `rcvlowat`: SO_RCVLOWAT 1 on both sockets (the kernel's default for a datagram socket: a datagram wakes its reader
  whole; Linux's datagram poll does not read the option);
- `busy_poll`: SO_BUSY_POLL 50 us on both sockets (needs CAP_NET_ADMIN above net.core.busy_read, 0 here; the kernel
  busy-polls only a device queue with a NAPI id, which loopback's datagrams do not carry: "Busy polling" in the
  kernel's networking documentation).

Per variant: the round trip's p50 / p99 / max (ms) and this client's and the echo's CPU per round trip (us).

--csharp: then a .NET client under Mono (benchmarks/ReceiveModes.cs, compiled with mcs) against one echo process, its
two ways of waiting for a reply alternated every half second for 4 x --seconds: awaiting UdpClient.ReceiveAsync (the
C# live client until issue 40's sixth round) and a thread of its own blocked in Socket.Receive (since).
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

SO_BUSY_POLL = 46  # asm-generic/socket.h (Python names neither option on every version)
SO_RCVLOWAT = socket.SO_RCVLOWAT
SPIN_S = 5e-4  # the client's spin
ECHO_SPIN_S = 3e-3  # the echo's: past the 2.8 ms between two pens at 360 Hz
VARIANTS = ("block", "spin", "echo_spin", "rcvlowat", "busy_poll")


def options(sock: socket.socket, variant: str) -> None:
    if variant == "rcvlowat":
        sock.setsockopt(socket.SOL_SOCKET, SO_RCVLOWAT, 1)
    elif variant == "busy_poll":
        sock.setsockopt(socket.SOL_SOCKET, SO_BUSY_POLL, 50)


def receive(sock: socket.socket, spin_s: float) -> tuple[bytes, tuple]:
    """The next datagram on the blocking socket: polled for (non-blocking) at most spin_s s, then waited for."""
    deadline = time.perf_counter() + spin_s
    sock.setblocking(False)
    try:
        while True:
            try:
                return sock.recvfrom(2048)
            except BlockingIOError:
                if time.perf_counter() >= deadline:
                    break
    finally:
        sock.setblocking(True)
    return sock.recvfrom(2048)


def echo(conn, variant: str) -> None:
    """Echo every datagram to its sender until an empty one; then send its CPU time since it was ready (s) over conn."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    options(sock, variant)
    sock.bind(("127.0.0.1", 0))
    conn.send(sock.getsockname()[1])
    spin_s = ECHO_SPIN_S if variant == "echo_spin" else 0.0
    cpu0 = time.process_time()
    while True:
        data, addr = receive(sock, spin_s)
        if not data:
            conn.send(time.process_time() - cpu0)
            return
        sock.sendto(data, addr)


def round_trips(variant: str, seconds: float, hz: float) -> tuple[np.ndarray, float, float]:
    """(round trips s, this process's and the echo's CPU per round trip s) of one variant against a fresh echo."""
    here, there = multiprocessing.Pipe()
    proc = multiprocessing.get_context("spawn").Process(target=echo, args=(there, variant), daemon=True)
    proc.start()
    server = ("127.0.0.1", here.recv())
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    options(sock, variant)
    spin_s = SPIN_S if variant == "spin" else 0.0
    payload = bytes(104)
    times = []
    cpu0, t0, k = time.process_time(), time.perf_counter(), 0
    while time.perf_counter() - t0 < seconds:
        sent = time.perf_counter()
        sock.sendto(payload, server)
        receive(sock, spin_s)
        times.append(time.perf_counter() - sent)
        k += 1
        time.sleep(max(0.0, t0 + k / hz - time.perf_counter()))
    cpu = (time.process_time() - cpu0) / k
    sock.sendto(b"", server)
    echo_cpu = here.recv() / k
    proc.join(2)
    return np.array(times), cpu, echo_cpu


def csharp(seconds: float, hz: float) -> None:
    """benchmarks/ReceiveModes.cs compiled and run against a fresh echo process; its lines printed."""
    with tempfile.TemporaryDirectory() as tmp:
        exe = Path(tmp) / "ReceiveModes.exe"
        build = subprocess.run(["mcs", "-warnaserror", f"-out:{exe}", str(Path(__file__).with_name("ReceiveModes.cs"))],
                               capture_output=True, text=True)
        if build.returncode != 0:
            raise SystemExit(f"--csharp: mcs failed: {build.stdout}{build.stderr}")
        here, there = multiprocessing.Pipe()
        proc = multiprocessing.get_context("spawn").Process(target=echo, args=(there, "block"), daemon=True)
        proc.start()
        try:
            run = subprocess.run(["mono", str(exe), str(here.recv()), str(seconds), str(hz)], capture_output=True,
                                 text=True, timeout=60 + 2 * seconds)
        finally:
            proc.kill()
        print("\n".join(f"C# {line}" for line in run.stdout.splitlines()) or f"C#: failed: {run.stderr.strip()}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=3.0, help="per variant and turn (default 3)")
    p.add_argument("--hz", type=float, default=360.0, help="round trips per second (default 360, the pens' rate)")
    p.add_argument("--csharp", action="store_true", help="then a Mono client's two ways of waiting (needs mcs, mono)")
    args = p.parse_args()
    print("load average " + ", ".join(f"{v:.2f}" for v in os.getloadavg()))
    for turn in range(2):
        for variant in VARIANTS:
            try:
                t, cpu, echo_cpu = round_trips(variant, args.seconds, args.hz)
            except PermissionError as exc:
                print(f"turn {turn + 1} {variant}: refused ({exc})")
                continue
            v = t * 1e3
            print(f"turn {turn + 1} {variant}: p50 {np.percentile(v, 50):.3f} / p99 {np.percentile(v, 99):.3f} / "
                  f"max {v.max():.3f} ms over {len(v)}; CPU per round trip: client {cpu * 1e6:.0f} us, "
                  f"echo {echo_cpu * 1e6:.0f} us", flush=True)
    if args.csharp:
        csharp(4 * args.seconds, args.hz)
    print("load average " + ", ".join(f"{v:.2f}" for v in os.getloadavg()))


if __name__ == "__main__":
    main()
