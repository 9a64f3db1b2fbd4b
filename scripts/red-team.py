#!/usr/bin/env python3
"""Attacks a real lsqsurfd as a tokenless client would, and checks that the server stays up,
bounded and answering. On its HTTP port (--http-listen):

  1. header flood: header lines without end, reconnecting whenever the server cuts the
     connection, until --flood-mib have been sent; the server's peak resident memory (VmHWM)
     must grow by less than 256 MiB and it must still answer;
  2. slowloris: 8 connections trickling a header byte every --trickle-s seconds and 80 silent
     ones, held for --hold-s seconds, while a fresh request every half second must be answered
     within 2 s;
  3. rebinding: a request naming a foreign Host is refused (421), one naming 127.0.0.1 is not.

On its gRPC port, through the lsqsurf client:

  4. repeats: 19.9M points at 19 positions must end within 2 s of their job's acceptance;
  5. big upload: a --upload-mib upload that is no Draco stream must be refused with the server's
     anonymous memory (heap, RssAnon sampled every 20 ms) growing by less than 256 MiB: the
     upload is checked from its spool file mapped, never read onto the heap;
  6. missing values: while a volume of 405k vertices, half of them without a value (NaN, which
     the server fills in), is submitted, small submissions must wait less than 1 s longer than
     they do on an idle server (lsqsurf-flood --missing-volume 74);
  7. shutdown: SIGTERM ends the server within 10 s.

  scripts/red-team.py [--flood-mib 300] [--hold-s 30] [--trickle-s 5] [--upload-mib 600]
                      [--only NAME,...] [--bin build/release/bin]

Prints one line per check and a closing 'N passed, N failed'; exits 1 if any failed. Starts its
own server on a free loopback port with a throwaway data directory; all traffic stays on
127.0.0.1. Not part of CI (the flood alone takes about a minute): run it by hand or from
scripts/soak.sh's neighbours after a release build.
"""
import argparse
import os
import re
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def status_mib(pid, field):
    """A memory figure of /proc/PID/status ("VmHWM", "RssAnon"), MiB; -1 when absent."""
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    return -1


def peak_rss_mib(pid):
    return status_mib(pid, "VmHWM")


class AnonPeak:
    """The peak of a process's anonymous resident memory (RssAnon: its heap, not its mapped
    files), sampled every 20 ms while in a `with` block."""

    def __init__(self, pid):
        self.pid, self.base, self.peak, self.running = pid, self.read(pid), 0, True

    @staticmethod
    def read(pid):
        return status_mib(pid, "RssAnon")

    def __enter__(self):
        self.peak = self.base
        def sample():
            while self.running:
                self.peak = max(self.peak, self.read(self.pid))
                time.sleep(0.02)
        self.thread = threading.Thread(target=sample, daemon=True)
        self.thread.start()
        return self

    def __exit__(self, *_):
        self.running = False
        self.thread.join()

    def grown_mib(self):
        return self.peak - self.base


def fresh_get(port, host="127.0.0.1", timeout=5.0):
    """A well-behaved request: (status code or 0, seconds taken)."""
    start = time.monotonic()
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
            s.sendall(f"GET /api/methods HTTP/1.1\r\nHost: {host}:{port}\r\nConnection: close\r\n\r\n".encode())
            reply = b""
            while b"\r\n" not in reply:
                chunk = s.recv(4096)
                if not chunk:
                    break
                reply += chunk
        status = int(reply.split(b" ", 2)[1]) if reply.startswith(b"HTTP/") else 0
    except (OSError, ValueError):
        status = 0
    return status, time.monotonic() - start


def flood(port, total_bytes):
    """Header lines without end; returns (bytes sent, connections used)."""
    line = b"X-Endless: " + b"x" * 1000 + b"\r\n"
    sent = connections = 0
    while sent < total_bytes:
        connections += 1
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
                s.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n")
                while sent < total_bytes:
                    s.sendall(line * 64)
                    sent += len(line) * 64
        except OSError:
            pass
    return sent, connections


def slowloris(port, hold_s, trickle_s):
    """Worst fresh-request latency while 8 trickle and 80 sit silent, and how many failed."""
    silent = [socket.create_connection(("127.0.0.1", port)) for _ in range(80)]
    trickling = []
    for _ in range(8):
        s = socket.create_connection(("127.0.0.1", port))
        s.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
        trickling.append(s)
    stop = threading.Event()

    def trickle():
        while not stop.wait(trickle_s):
            for s in trickling:
                try:
                    s.send(b"x")
                except OSError:
                    pass

    thread = threading.Thread(target=trickle)
    thread.start()
    worst, failed, end = 0.0, 0, time.monotonic() + hold_s
    while time.monotonic() < end:
        status, seconds = fresh_get(port)
        worst = max(worst, seconds)
        failed += status != 200
        time.sleep(0.5)
    stop.set()
    thread.join()
    for s in silent + trickling:
        s.close()
    return worst, failed


def repeated_points_cloud(path, parts=19, per_part=1 << 20):
    """A binary PLY of `parts` blocks, each one position repeated `per_part` times."""
    with open(path, "wb") as f:
        f.write(b"ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % (parts * per_part))
        f.write(b"property float x\nproperty float y\nproperty float z\nend_header\n")
        for k in range(parts):
            f.write(struct.pack("<fff", k % 4 * 0.1, k // 4 * 0.1, 0.05 * k) * per_part)


def not_draco(path, mib):
    """A .drc file the client sends as it is: Draco's magic, then bytes no decoder accepts."""
    block = bytes(range(256)) * 4096
    with open(path, "wb") as f:
        f.write(b"DRACO\x09\x09")
        for _ in range(mib):
            f.write(block)


def accepted_to_end_seconds(log_path):
    """Seconds from the job's 'accepted' line to its end in the server's log, or None."""
    stamps = {}
    with open(log_path) as log:
        for line in log:
            for event in ("accepted", "succeeded", "failed", "cancelled"):
                if f"] {event}" in line:
                    stamps.setdefault(event, line[:23])
    if "accepted" not in stamps or len(stamps) < 2:
        return None
    parse = lambda text: time.mktime(time.strptime(text[:19], "%Y-%m-%d %H:%M:%S")) + float(text[19:23])
    end = min(parse(v) for k, v in stamps.items() if k != "accepted")
    return end - parse(stamps["accepted"])


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--flood-mib", type=int, default=300)
    parser.add_argument("--hold-s", type=float, default=30)
    parser.add_argument("--trickle-s", type=float, default=5)
    parser.add_argument("--upload-mib", type=int, default=600)
    parser.add_argument("--only", default="", help="comma-separated checks to run (flood, slowloris, rebinding, "
                        "repeats, upload, missing); default all")
    parser.add_argument("--bin", default="build/release/bin")
    args = parser.parse_args()
    chosen = set(filter(None, args.only.split(",")))
    wanted = lambda name: not chosen or name in chosen
    work = tempfile.mkdtemp(prefix="lsqsurf-http-attack.")
    grpc_port, http_port = free_port(), free_port()
    server = subprocess.Popen(
        [os.path.join(args.bin, "lsqsurfd"), "--listen", f"127.0.0.1:{grpc_port}", "--http-listen",
         f"127.0.0.1:{http_port}", "--data-dir", os.path.join(work, "data"), "--max-job-mib", "1000000"],
        stdout=subprocess.DEVNULL, stderr=open(os.path.join(work, "server.log"), "w"))
    # Memory estimates would refuse the repeated cloud on a small machine before it runs; the
    # attack is on what runs.
    results = []

    def check(name, ok, detail):
        results.append(ok)
        print(f"{'PASS' if ok else 'FAIL'} {name}: {detail}", flush=True)

    try:
        for _ in range(100):
            if fresh_get(http_port)[0] == 200:
                break
            time.sleep(0.1)
        client = [os.path.join(args.bin, "lsqsurf"), "--server", f"127.0.0.1:{grpc_port}", "-q"]
        if wanted("flood"):
            before = peak_rss_mib(server.pid)
            start = time.monotonic()
            sent, connections = flood(http_port, args.flood_mib << 20)
            grown = peak_rss_mib(server.pid) - before
            status, _ = fresh_get(http_port)
            check("header flood", server.poll() is None and status == 200 and grown < 256,
                  f"{sent / 2**20:.0f} MiB over {connections} connections in {time.monotonic() - start:.1f} s; "
                  f"peak memory +{grown:.1f} MiB; server {'up' if server.poll() is None else 'DOWN'}, answers {status}")
        if wanted("slowloris"):
            worst, failed = slowloris(http_port, args.hold_s, args.trickle_s)
            check("slowloris", worst < 2.0 and failed == 0,
                  f"8 trickling + 80 silent for {args.hold_s:.0f} s: slowest fresh answer {worst * 1000:.0f} ms, "
                  f"{failed} unanswered")
        if wanted("rebinding"):
            foreign, _ = fresh_get(http_port, host="rebound.example")
            own, _ = fresh_get(http_port)
            check("rebinding", foreign == 421 and own == 200, f"Host rebound.example: {foreign}; Host 127.0.0.1: {own}")
        if wanted("repeats"):
            cloud = os.path.join(work, "repeats.ply")
            repeated_points_cloud(cloud)
            before = peak_rss_mib(server.pid)
            subprocess.run(client + ["reconstruct", cloud, "-o", os.path.join(work, "repeats-mesh.ply")], timeout=600,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            seconds = accepted_to_end_seconds(os.path.join(work, "server.log"))
            check("repeats", seconds is not None and seconds < 2.0,
                  f"19.9M points at 19 positions: ended {seconds if seconds is None else round(seconds, 2)} s after "
                  f"acceptance; peak memory +{peak_rss_mib(server.pid) - before:.0f} MiB")
        if wanted("upload"):
            garbage = os.path.join(work, "not-draco.drc")
            not_draco(garbage, args.upload_mib)
            with AnonPeak(server.pid) as anon:
                done = subprocess.run(client + ["submit", garbage], stdout=subprocess.DEVNULL,
                                      stderr=subprocess.PIPE, text=True, timeout=600)
            os.remove(garbage)
            refused = done.returncode != 0 and done.stderr.rstrip().endswith("(3)")  # INVALID_ARGUMENT
            check("big upload", refused and anon.grown_mib() < 256,
                  f"{args.upload_mib} MiB that is no Draco stream: {'refused' if refused else 'NOT refused'}; "
                  f"server heap peak +{anon.grown_mib():.0f} MiB")
        if wanted("missing"):
            # lsqsurf-flood sends the NaN values as they are (lsqsurf itself fills them in first).
            done = subprocess.run([os.path.join(args.bin, "lsqsurf-flood"), "--server", f"127.0.0.1:{grpc_port}",
                                   "--missing-volume", "74"], capture_output=True, text=True, timeout=600)
            delay = re.search(r"delayed by (-?\d+) ms", done.stdout)
            check("missing values", done.returncode == 0 and delay is not None and int(delay.group(1)) < 1000,
                  " ".join(done.stdout.split()) or done.stderr.strip())
    finally:
        start = time.monotonic()
        server.terminate()
        try:
            server.wait(timeout=10)
            check("shutdown", True, f"SIGTERM ended the server in {time.monotonic() - start:.1f} s")
        except subprocess.TimeoutExpired:
            server.kill()
            check("shutdown", False, "SIGTERM did not end the server within 10 s")
        shutil.rmtree(work, ignore_errors=True)
    print(f"{sum(results)} passed, {len(results) - sum(results)} failed")
    return 0 if all(results) else 1


if __name__ == "__main__":
    sys.exit(main())
