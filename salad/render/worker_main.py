"""The render worker process (`python -m salad.render.worker_main FD`, started by salad.render.workers.start):
it draws the shares of videos that the process at the other end of socket FD hands it, and sends the
frames back, until that socket closes."""
from __future__ import annotations

import socket
import sys

import numpy as np

from .engine import engine
from .video import Scene, draw_panels, warm_up
from .workers import recv_message, send_message


def scene_from_message(header: dict, arrays: list[np.ndarray]) -> Scene:
    """The Scene that workers.scene_message described."""
    values = {k: v for k, v in header.items() if k != "array_names"}
    values["size"] = tuple(values["size"])
    values["motions"] = []
    for name, a in zip(header["array_names"], arrays):
        if name == "motions":
            values["motions"].append(a)
        else:
            values[name] = a
    return Scene(**values)


def serve(sock: socket.socket) -> None:
    warm_up()
    send_message(sock, {"ready": True})
    while True:
        try:
            header, arrays = recv_message(sock)
        except EOFError:
            return
        number = header.get("job")
        try:
            scene = scene_from_message(header["scene"], arrays)
            panels = scene.panels()
            with engine() as eng:
                eng.renderer.samples = int(header["samples"])
                frames = range(header["lo"], header["hi"])
                for t, images in draw_panels(eng, panels, header["panels"], frames, scene.size):
                    send_message(sock, {"job": number, "t": t, "panels": list(images)}, list(images.values()))
            send_message(sock, {"job": number})
        except (EOFError, BrokenPipeError, ConnectionResetError):
            return
        except Exception as exc:        # reported, and the share is drawn by the other process
            send_message(sock, {"job": number, "error": f"{type(exc).__name__}: {exc}"})


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1 or not argv[0].isdigit():
        raise SystemExit("usage: python -m salad.render.worker_main FD (started by salad.render.workers.start)")
    sock = socket.socket(fileno=int(argv[0]))
    try:
        serve(sock)
    finally:
        sock.close()


if __name__ == "__main__":
    main()
