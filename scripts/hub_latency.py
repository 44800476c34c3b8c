#!/usr/bin/env python3
"""A good client's latency through the hub beside many others (issue 35, docs/BENCHMARKS.md).

Usage: scripts/hub_latency.py CANPOS_BIN [--bad N] [--mode never|reading] [--load FPS]
                              [--warmup FRAMES] [--count K] [--port P]

Starts `CANPOS_BIN bus serve` on a free loopback port, then:
  * N other clients (a child process) open channel `lat` in raw mode; `never`: they read the
    handshake and nothing after it (their buffers fill up), `reading`: they read everything;
  * a load client sends FPS frames/s (id 0x181, 8 bytes) for the whole run, like a sensor's
    TPDO; before the measurement WARMUP frames go out as fast as the bus takes them, so that a
    never-reading client's socket and queue are full when the measurement starts;
  * a good sender and a good receiver: the sender sends K frames (id 0x7E0, the sequence number
    in the data), one at a time, 5 ms apart; the receiver times each from its send to its
    arrival (a frame not seen within 2 s is counted lost).
Prints p50 / p99 / max in ms, lost frames, the hub's RSS and the load average. Bounded: at
most K × 2 s of measuring; every socket closes at the end.
"""
import argparse, os, resource, selectors, signal, socket, subprocess, sys, threading, time

ap = argparse.ArgumentParser()
ap.add_argument("canpos")
ap.add_argument("--bad", type=int, default=2000)
ap.add_argument("--mode", choices=["never", "reading"], default="never")
ap.add_argument("--load", type=float, default=1000.0)
ap.add_argument("--warmup", type=int, default=20000)
ap.add_argument("--count", type=int, default=2000)
ap.add_argument("--port", type=int, default=0)
ap.add_argument("--settle", type=float, default=60.0,
                help="after the warm-up, wait up to this many seconds for the hub to be idle "
                     "but for the load (its CPU below 30 %% of a core over 1 s): the other "
                     "clients' sockets are full, or their backlog written")
args = ap.parse_args()

# 12,000 sockets and more: raise the soft limit to the hard one (the hub inherits it).
soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
resource.setrlimit(resource.RLIMIT_NOFILE, (min(65536, hard), hard))

def free_port():
    s = socket.socket(); s.bind(("127.0.0.1", 0)); p = s.getsockname()[1]; s.close(); return p

port = args.port or free_port()
hub = subprocess.Popen([args.canpos, "bus", "serve", "--listen", f"127.0.0.1:{port}",
                        "--max-clients", str(args.bad + 16), "--stats-interval", "0"],
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

def rss(pid):
    for l in open(f"/proc/{pid}/status"):
        if l.startswith("VmRSS:"):
            return int(l.split()[1])
    return 0

def connect(channel="lat", rcvbuf=None):
    end = time.time() + 10
    while True:
        try:
            s = socket.socket()
            if rcvbuf:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
            s.settimeout(10)
            s.connect(("127.0.0.1", port))
            break
        except OSError:
            s.close()
            if time.time() > end:
                raise
            time.sleep(0.05)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    buf = b""
    for cmd in (None, f"< open {channel} >".encode(), b"< rawmode >"):
        if cmd:
            s.sendall(cmd)
        while b">" not in buf:
            buf += s.recv(64)
        buf = buf[buf.index(b">") + 1:]
    # Its answer says the hub has handled the handshake.
    s.sendall(b"< echo >")
    return s

def bad_clients(n, mode, ready_w):
    """Child process: n clients, never reading (or reading everything) until killed."""
    conns = []
    for _ in range(n):
        conns.append(connect())
    os.write(ready_w, b"1")
    if mode == "never":
        signal.pause()
    sel = selectors.DefaultSelector()
    for c in conns:
        c.setblocking(False)
        sel.register(c, selectors.EVENT_READ)
    while True:
        for key, _ in sel.select():
            try:
                if not key.fileobj.recv(1 << 16):
                    sel.unregister(key.fileobj)
            except BlockingIOError:
                pass

t0 = time.time()
r, w = os.pipe()
child = os.fork()
if child == 0:
    try:
        bad_clients(args.bad, args.mode, w)
    finally:
        os._exit(0)
os.close(w)
if args.bad:
    assert os.read(r, 1) == b"1", "the other clients did not connect"
print(f"{args.bad} {args.mode} clients connected in {time.time() - t0:.1f} s; hub RSS {rss(hub.pid)} KiB",
      flush=True)

load = connect()
sender = connect()
receiver = connect()
stop = threading.Event()

def load_loop():
    frame = b"< send 181 8 01 02 03 04 05 06 07 08 >"
    # Warm-up: as fast as the 1 Mbit/s bus takes them (about 7,000 8-byte frames/s).
    left = args.warmup
    while left > 0 and not stop.is_set():
        k = min(left, 70)
        load.sendall(frame * k)
        left -= k
        time.sleep(0.01)
    warm.set()
    if args.load <= 0:
        return
    batch = max(1, int(args.load / 100))
    nxt = time.monotonic()
    while not stop.is_set():
        load.sendall(frame * batch)
        nxt += batch / args.load
        time.sleep(max(0.0, nxt - time.monotonic()))

warm = threading.Event()
lt = threading.Thread(target=load_loop, daemon=True)
lt.start()
warm.wait()
time.sleep(0.5)
print(f"warm-up of {args.warmup} frames done; hub RSS {rss(hub.pid)} KiB", flush=True)

def cpu(pid):
    f = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")

t_settle = time.time()
while time.time() - t_settle < args.settle:
    c0 = cpu(hub.pid)
    time.sleep(1)
    if cpu(hub.pid) - c0 < 0.3:
        break
print(f"settled after {time.time() - t_settle:.1f} s; hub RSS {rss(hub.pid)} KiB", flush=True)

receiver.settimeout(2)
lat, lost, buf, series = [], 0, b"", []
for seq in range(args.count):
    tag = f"{seq & 0xFFFFFFFF:08X}"
    data = " ".join(tag[i:i + 2] for i in range(0, 8, 2))
    t = time.perf_counter()
    sender.sendall(f"< send 7E0 4 {data} >".encode())
    want = f"< frame 7E0 ".encode()
    got = False
    end = t + 2
    while time.perf_counter() < end:
        i = buf.find(want)
        while i >= 0:
            j = buf.find(b">", i)
            if j < 0:
                break
            if buf[i:j].split()[-1].decode() == tag:
                got = True
                buf = buf[j + 1:]
                break
            i = buf.find(want, j)
        if got:
            break
        # Keep only a possible partial element.
        k = buf.rfind(b"<")
        buf = buf[k:] if k >= 0 else b""
        try:
            chunk = receiver.recv(1 << 16)
        except socket.timeout:
            break
        if not chunk:
            break
        buf += chunk
    if got:
        lat.append((time.perf_counter() - t) * 1000)
        series.append((seq, lat[-1]))
    else:
        lost += 1
    time.sleep(0.005)

stop.set()
hub_rss = rss(hub.pid)
load_avg = os.getloadavg()
os.kill(child, signal.SIGKILL)
os.waitpid(child, 0)
hub.terminate()
try:
    hub.wait(10)
except subprocess.TimeoutExpired:
    hub.kill()
worst = sorted(series, key=lambda x: -x[1])[:8]
print("worst (frame #, ms):", ", ".join(f"#{i} {ms:.1f}" for i, ms in worst), flush=True)
later = sorted(ms for i, ms in series if i >= 50)
if later:
    print(f"from frame #50 on: p50 {later[len(later) // 2]:.2f} ms, "
          f"p99 {later[min(len(later) - 1, int(0.99 * len(later)))]:.2f} ms, max {later[-1]:.2f} ms",
          flush=True)
lat.sort()
q = lambda p: lat[min(len(lat) - 1, int(p * len(lat)))] if lat else float("nan")
print(f"bad={args.bad} mode={args.mode} load={args.load:g}/s count={args.count}: "
      f"p50 {q(0.5):.2f} ms, p99 {q(0.99):.2f} ms, max {lat[-1] if lat else float('nan'):.2f} ms, "
      f"lost {lost}; hub RSS {hub_rss} KiB; load avg {load_avg[0]:.2f} {load_avg[1]:.2f}", flush=True)
