"""Repeats python-can socketcand handshakes against a canpos hub while a TH sends TPDO1 at 1 kHz
(event timer 1 ms) and a python-can notifier reads them; prints how many handshakes failed.

    python scripts/handshake_loop.py CANPOS_BIN [N] [old]

`old`: the binary has no `--hub` option (before docs/SOCKETCAND.md). Uses 127.0.0.1:29800 and
/tmp/handshake-loop-state. docs/SOCKETCAND.md, "The python-can handshake under traffic".
"""
import socket, subprocess, sys, time, struct
import can
BIN = sys.argv[1]; N = int(sys.argv[2]) if len(sys.argv) > 2 else 200
port = 29800
hub = subprocess.Popen([BIN, "bus", "serve", "--listen", f"127.0.0.1:{port}"], stderr=subprocess.DEVNULL)
time.sleep(0.5)
sensor = subprocess.Popen([BIN, "run", "--model", "th", "--bus", f"socketcand://127.0.0.1:{port}/can0",
    *([] if len(sys.argv) > 3 else ["--hub", "never"]), "--nmt", "operational", "--state-dir", "/tmp/handshake-loop-state", "--ideal"], stderr=subprocess.DEVNULL)
time.sleep(1.0)
m = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="can0")
# TPDO1 event timer 1 ms (0x1800:5 = 1)
m.send(can.Message(arbitration_id=0x67F, data=[0x2B, 0x00, 0x18, 0x05, 1, 0, 0, 0], is_extended_id=False))
t0 = time.time(); n = 0
while time.time() - t0 < 1:
    msg = m.recv(0.1)
    if msg is not None and msg.arbitration_id == 0x1FF: n += 1
print("TPDO rate in 1 s:", n)
count=[0]
class L(can.Listener):
    def on_message_received(self, msg):
        count[0]+=1
notifier = can.Notifier(m, [L()])
fails = []
import threading
def work():
    for i in range(N // 4):
        try:
            b = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="can0")
            time.sleep(0.01)
            b.shutdown()
        except Exception as e:
            fails.append(str(e)[:150])
ts = [threading.Thread(target=work) for _ in range(4)]
[t.start() for t in ts]; [t.join() for t in ts]
print(f"{len(fails)} of {N} handshakes failed")
for f in fails[:5]: print("  ", f)
notifier.stop(); print("notifier got", count[0]); m.shutdown(); sensor.terminate(); hub.terminate(); sensor.wait(); hub.wait()
