"""The MeshCat server that `MeshcatVisualizer` starts: meshcat-python's bridge (a ZeroMQ socket
for commands, a web server for the browser), run as a child process that

- listens on one address, 127.0.0.1 unless the caller names another (meshcat-python's own
  server binds its web port on every interface), and
- ends with its parent: it exits when its standard input reaches end-of-file, which happens
  when the parent exits, killed included; `stop` ends it earlier.

Run as a script (by path, no package import: the child starts in a fraction of a second).
"""

from __future__ import annotations

import atexit
import os
import subprocess
import sys
import threading


def start(host: str = "127.0.0.1"):
    """Start a MeshCat server listening on `host`; returns (process, zmq_url, web_url)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))  # where the parent finds meshcat
    process = subprocess.Popen([sys.executable, "-P", "-u", __file__, host], stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                               start_new_session=True)  # an interrupted notebook cell leaves it running
    lines = [process.stdout.readline().decode().strip() for _ in range(2)]
    if not (lines[0].startswith("zmq_url=") and lines[1].startswith("web_url=")):
        stop(process)
        raise RuntimeError(f"the MeshCat server on {host} did not start: {process.stderr.read().decode().strip()}")
    atexit.register(stop, process)
    return process, lines[0].removeprefix("zmq_url="), lines[1].removeprefix("web_url=")


def stop(process) -> None:
    """End a server `start` began (if still running)."""
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    for stream in (process.stdin, process.stdout, process.stderr):
        stream.close()


def _serve(host: str) -> None:
    from meshcat.servers.zmqserver import ZMQWebSocketBridge

    class Bridge(ZMQWebSocketBridge):
        def make_app(self):  # meshcat-python listens on every interface; only on `host` here
            app = super().make_app()
            listen = app.listen
            app.listen = lambda port, **kwargs: listen(port, address=self.host, **kwargs)
            return app

    bridge = Bridge(host=host)
    print(f"zmq_url={bridge.zmq_url}\nweb_url={bridge.web_url}", flush=True)
    quiet = os.open(os.devnull, os.O_WRONLY)  # nobody reads the pipes any more: never block on them
    os.dup2(quiet, 1)
    os.dup2(quiet, 2)
    threading.Thread(target=_exit_with_parent, daemon=True).start()
    bridge.run()


def _exit_with_parent() -> None:
    sys.stdin.buffer.read()  # returns at end-of-file: the parent closed its end, or died
    os._exit(0)


if __name__ == "__main__":
    _serve(sys.argv[1])
