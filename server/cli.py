"""``edmcgs-serve``: serve a scene over HTTP and a websocket.

    edmcgs-serve                                             # the bundled demo, replayed in a loop
    edmcgs-serve --replay rec.h5 --checkpoint scene.ckpt --loop
    edmcgs-serve --replay rec.aedat4 --checkpoint scene.ckpt --speed 0.5
    edmcgs-serve --live --checkpoint scene.ckpt              # a DAVIS346 over USB
    edmcgs-serve --replay street.aedat4                      # no checkpoint: learn one while serving
    edmcgs-serve --live                                      # (renders at once; a model within a minute)
    edmcgs-serve --checkpoint scene.ckpt                     # no sensor: a checkpoint without events,
                                                             # its span played in a loop (--speed)
    edmcgs-serve --ray scenes.yaml                           # many scenes on Ray Serve (extra: ray)

Every flag is also an ``EDMCGS_<NAME>`` environment variable (flags win); ``EDMCGS_TOKEN`` makes every
route require ``Authorization: Bearer <token>``.
"""

from __future__ import annotations

import argparse
import errno
import logging
import os
import signal
import socket
import sys

from pydantic import ValidationError

from edmcgs import __version__
from edmcgs.errors import EdmcgsError, InvalidInputError
from edmcgs.filekind import check_checkpoint, check_recording


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="edmcgs-serve", description=__doc__.split("\n\n")[0],
                                epilog="Settings without a flag: EDMCGS_MAX_WIDTH, EDMCGS_RENDER_WORKERS, "
                                       "... (see edmcgs.server.settings).")
    p.add_argument("--replay", metavar="FILE", help="recording to replay: .aedat4, or .h5/.hdf5")
    p.add_argument("--checkpoint", metavar="CKPT",
                   help="EdMCGS checkpoint of the scene (none with --replay or --live: learn one while "
                        "serving)")
    p.add_argument("--intrinsics", metavar="FX,FY,CX,CY|CALIB.json",
                   help="learning without a checkpoint: the camera (default: the recording's, else fx = fy "
                        "= width, centred)")
    p.add_argument("--learn-dir", metavar="DIR", help="learning without a checkpoint: where the learnt "
                                                       "checkpoints go (default ./edmcgs-learned)")
    p.add_argument("--speed", type=float, help="replay speed, a real-time factor (default 1); without a "
                                               "sensor, the speed the span plays at")
    p.add_argument("--loop", action="store_true", default=None, help="replay in a loop")
    p.add_argument("--live", action="store_true", default=None, help="read a DAVIS346 over USB")
    p.add_argument("--host", help="interface to bind (default 127.0.0.1)")
    p.add_argument("--port", type=int, help="TCP port (default 8000; 0: any free port)")
    p.add_argument("--device", help="torch device of the model: cpu (default), cuda, cuda:1 ...")
    p.add_argument("--ray", metavar="CONFIG", help="serve the scenes of a YAML config on Ray Serve (the "
                                                   "'ray' extra; joins RAY_ADDRESS, else a local Ray)")
    p.add_argument("--ray-cpus", type=int, metavar="N", help="CPUs of the local Ray --ray starts")
    p.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))
    p.add_argument("--online-finetune-steps", type=int, metavar="N",
                   help="after each online correction, N Adam steps fine-tuning a copy of g_phi for the "
                        "span past the checkpoint (default 0: off; EDMCGS_ONLINE_FINETUNE_LR sets the step)")
    p.add_argument("--online-spawn", type=int, metavar="N",
                   help="a real-preset checkpoint's online anchors add up to N static Gaussians where the "
                        "frame differs from the render (default 0: off)")
    p.add_argument("--version", action="version", version=f"edmcgs-serve {__version__}")
    return p


class RedactQueries(logging.Filter):
    """Keep the token out of uvicorn's access and websocket lines: each request target is logged without
    its query (``auth.loggable_target``), never redacted parameter by parameter; the configured token
    is replaced wherever else it appears."""

    def __init__(self, token: str | None = None):
        super().__init__()
        self.token = token

    def filter(self, record: logging.LogRecord) -> bool:
        from edmcgs.server.auth import loggable_target  # loaded by then: the app imports it

        if isinstance(record.args, tuple):
            record.args = tuple(loggable_target(a, self.token) if isinstance(a, str) else a
                                for a in record.args)
        if self.token and isinstance(record.msg, str):
            record.msg = record.msg.replace(self.token, "***")
        return True


def redact_logs(token: str | None) -> None:
    """Install ``RedactQueries`` on uvicorn's loggers (access lines, and websocket accept lines)."""
    for name in ("uvicorn.access", "uvicorn.error"):
        logging.getLogger(name).addFilter(RedactQueries(token))


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.ray is not None:
        return _main_ray(args)
    # Before torch and numba start their OpenMP pools: waiting threads sleep instead of spinning. On a
    # small shared CPU, spinning workers of two pools (torch's, numba's) and two render threads starve
    # each other, and the deformation slows by an order of magnitude. An explicit OMP_WAIT_POLICY in the
    # environment wins.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from edmcgs.server.settings import Settings

    flags = {k: v for k, v in vars(args).items() if v is not None and k != "log_level"}
    logging.basicConfig(level=args.log_level.upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        settings = Settings(**flags)
    except ValidationError as exc:
        for err in exc.errors():
            where = ".".join(str(p) for p in err["loc"]) or "settings"
            print(f"edmcgs-serve: {where}: {err['msg']}", file=sys.stderr)
        return 2
    try:
        check_inputs(settings)
    except EdmcgsError as exc:
        print(f"edmcgs-serve: {exc}", file=sys.stderr)
        return 1
    import uvicorn

    from edmcgs.server.app import create_app
    from edmcgs.server.connections import raise_fd_limit, uvicorn_config
    from edmcgs.server.service import Service

    if settings.token is None and settings.host not in ("127.0.0.1", "localhost", "::1"):
        logging.getLogger("edmcgs.server").warning(
            "serving on %s without EDMCGS_TOKEN: anyone who can reach this port can use the service",
            settings.host)
    redact_logs(settings.token.get_secret_value() if settings.token is not None else None)
    # Open before serving, so a bad checkpoint, recording or device is one line, not a traceback.
    try:
        service = Service.open(settings)
    except EdmcgsError as exc:
        print(f"edmcgs-serve: {exc}", file=sys.stderr)
        return 1
    app = create_app(settings, service_factory=lambda _settings: service)
    raise_fd_limit()
    server = uvicorn.Server(uvicorn_config(app, settings, log_level=args.log_level))
    stopped_by = []  # the signals that stopped it: uvicorn's own handler, wrapped to remember them
    handle_exit = server.handle_exit
    server.handle_exit = lambda sig, frame: (stopped_by.append(sig), handle_exit(sig, frame))
    try:
        server.run()
    except KeyboardInterrupt:  # uvicorn re-raises Ctrl-C after its graceful shutdown
        return 130
    finally:
        if not server.started:  # the lifespan never ran: close what was opened here
            service.close()
    if stopped_by[:1] == [signal.SIGINT]:  # uvicorn's re-raise may find asyncio's main task done
        return 130
    return 0 if server.started else 1


def check_inputs(settings) -> None:
    """What can be checked before torch is imported and the model loaded (seconds): the files are what
    their flags say, and the port is free. An EdmcgsError naming the first problem."""
    if settings.replay is not None:
        check_recording(settings.replay, hint="pass it as --checkpoint (--replay takes its recording)")
    if settings.checkpoint is not None:
        check_checkpoint(settings.checkpoint, verify=True,
                         hint="pass it as --replay (--checkpoint takes the model trained on it)")
    check_port(settings.host, settings.port)


def check_port(host: str, port: int) -> None:
    """InvalidInputError unless ``host:port`` can be bound now (port 0 is always free), tried as uvicorn
    binds it (SO_REUSEADDR, so a closed connection's TIME_WAIT is no obstacle)."""
    if port == 0:
        return
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except socket.gaierror as exc:
        raise InvalidInputError(f"--host {host!r}: {exc.strerror}") from None
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise InvalidInputError(f"port {port} on {host} is in use (another edmcgs-serve?): give "
                                        "--port N or EDMCGS_PORT=N (0: any free port)") from None
            raise InvalidInputError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None


def _main_ray(args: argparse.Namespace) -> int:
    """``--ray CONFIG``: the scenes' own settings come from the config, so the one-scene flags are refused."""
    given = [f"--{k.replace('_', '-')}" for k, v in vars(args).items()
             if v is not None and k not in ("ray", "ray_cpus", "log_level")]
    if given:
        print(f"edmcgs-serve: {', '.join(given)} cannot be combined with --ray: each scene's settings are in "
              "its config", file=sys.stderr)
        return 2
    logging.basicConfig(level=args.log_level.upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        from edmcgs.server.ray_serve.app import main as ray_main
    except ImportError as exc:
        print(f"edmcgs-serve: --ray needs the 'ray' extra (pip install 'edmcgs[ray]'): {exc}",
              file=sys.stderr)
        return 2
    try:
        return ray_main(args.ray, num_cpus=args.ray_cpus)
    except EdmcgsError as exc:
        print(f"edmcgs-serve: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
