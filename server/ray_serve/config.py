"""The YAML file that lists the scenes served on Ray, validated before anything starts.

    http: {host: 127.0.0.1, port: 8000}       # Serve's HTTP proxy (optional); the host also decides the
                                               # Host names the gateway and the scenes answer to, as for
                                               # edmcgs-serve (or allowed_hosts: [...])
    scenes:
      - name: street                           # its routes live under /scenes/street/
        checkpoint: street.ckpt                # relative paths: from the config file's folder
        replay: street.h5                      # or live: true, or neither (a checkpoint without events);
                                               # live: true with a replay plays it as a camera
        loop: true
        replicas: 2                            # render replicas, each with its ring; a replay is
                                               # each one's own, a live source one shared by all
        max_replicas: 4                        # optional: Serve scales between replicas and this by load
        cpus_per_replica: 1
        settings: {render_workers: 2}          # any other edmcgs-serve setting (edmcgs.server.settings)

``demo: true`` in place of checkpoint and replay serves the bundled demo scene. Errors name the file,
the scene and the field.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from edmcgs.errors import InvalidInputError

NAME = re.compile(r"^[a-z0-9][a-z0-9_-]{0,62}$")
OWN_FIELDS = {"checkpoint", "replay", "live", "loop", "speed", "host", "port"}
"""Settings given by the scene's own keys or by the gateway, never under ``settings``."""


class HttpOptions(BaseModel):
    """Where Serve's HTTP proxy listens (every node's proxy, on a cluster; under ``serve run`` or KubeRay
    Serve's own config sets it). ``host`` also gives the Host allowlist of the gateway's own pages and
    the scenes' default: loopback names for a loopback host, any name otherwise; ``allowed_hosts`` sets
    it (a scene's ``settings.allowed_hosts`` sets the scene's own)."""

    model_config = ConfigDict(extra="forbid")
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    allowed_hosts: list[str] | None = Field(None, description="Host names the gateway and, unless they "
                                            "name their own, the scenes answer to (['*']: any)")


class SceneConfig(BaseModel):
    """One scene: a checkpoint (none: a cold start, learnt while it serves) and its event source, served by
    ``replicas`` render replicas."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field(description="URL name: lowercase letters, digits, '-' and '_'")
    demo: bool = Field(False, description="serve the bundled demo scene (no checkpoint, no replay)")
    checkpoint: Path | None = None
    replay: Path | None = None
    live: bool = Field(False, description="a camera (or, with replay, the recording played as one), "
                                          "read once and shared by the scene's replicas")
    loop: bool = False
    speed: float = Field(1.0, gt=0, le=1e6)
    replicas: int = Field(1, ge=1, le=1024)
    max_replicas: int | None = Field(None, ge=1, le=1024,
                                     description="scale with load between replicas and this many")
    cpus_per_replica: float = Field(1.0, ge=0, le=1024)
    max_queued: int = Field(64, ge=1, le=100_000,
                        description="requests waiting for a replica before the gateway answers 503 busy")
    settings: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _check(self) -> SceneConfig:
        if not NAME.match(self.name):
            raise ValueError(f"name {self.name!r}: use 1-63 lowercase letters, digits, '-' or '_', "
                             "starting with a letter or digit (it is part of the URL)")
        if self.demo and (self.checkpoint or self.replay or self.live):
            raise ValueError("demo: true serves the bundled scene; give no checkpoint, replay or live")
        if not self.demo and self.checkpoint is None and not self.live:
            raise ValueError("give a checkpoint (or demo: true); a scene with none learns from a cold start, "
                             "which needs the one stream its learner and replicas share: live: true (with "
                             "replay, the recording played as a camera)")
        if self.checkpoint is None and self.loop:
            raise ValueError("a cold start learns one pass of the stream: loop needs a checkpoint")
        if self.live and self.speed != 1.0:
            raise ValueError(f"speed {self.speed}: a live scene runs at the camera's pace (a replay played "
                             "as a camera is stamped with the wall clock); give speed 1 or leave it out")
        if self.max_replicas is not None and self.max_replicas < self.replicas:
            raise ValueError(f"max_replicas ({self.max_replicas}) is below replicas ({self.replicas})")
        own = sorted(OWN_FIELDS & self.settings.keys())
        if own:
            raise ValueError(f"settings: {', '.join(own)} are the scene's own keys (or the gateway's), "
                             "not settings")
        return self

    @property
    def cold(self) -> bool:
        """A cold start: no checkpoint, one learner for the scene (``learner.py``)."""
        return not self.demo and self.checkpoint is None

    def settings_dict(self) -> dict[str, Any]:
        """The keyword arguments of this scene's ``edmcgs.server.settings.Settings``."""
        out: dict[str, Any] = dict(self.settings)
        if not self.demo:
            out.update(checkpoint=None if self.cold else str(self.checkpoint), live=self.live, loop=self.loop,
                       speed=self.speed)
            if self.replay is not None and not self.live:  # a live scene's replay is its ingest's
                out["replay"] = str(self.replay)
        else:
            out["speed"] = self.speed
        return out


class RayConfig(BaseModel):
    """The whole file: the HTTP options and at least one scene, names unique."""

    model_config = ConfigDict(extra="forbid")
    http: HttpOptions = Field(default_factory=HttpOptions)
    scenes: list[SceneConfig] = Field(min_length=1)

    @model_validator(mode="after")
    def _unique(self) -> RayConfig:
        seen: set[str] = set()
        for scene in self.scenes:
            if scene.name in seen:
                raise ValueError(f"two scenes are named {scene.name!r}: names must be unique")
            seen.add(scene.name)
        return self

    def scene(self, name: str) -> SceneConfig:
        return next(s for s in self.scenes if s.name == name)


def _where(loc: tuple, data: Any) -> str:
    """``scenes[1] (street).replicas`` from a pydantic error location."""
    parts, node = [], data
    for key in loc:
        if isinstance(key, int):
            name = node[key].get("name") if isinstance(node, list) and key < len(node) and isinstance(
                node[key], dict) else None
            parts[-1] += f"[{key}]" + (f" ({name})" if name else "")
        else:
            parts.append(str(key))
        try:
            node = node[key]
        except (KeyError, IndexError, TypeError):
            node = None
    return ".".join(parts)


def parse_config(data: Any, *, base: Path, source: str = "config") -> RayConfig:
    """Validate ``data`` (the parsed YAML); relative paths are taken from ``base``; files must exist."""
    if not isinstance(data, dict):
        raise InvalidInputError(f"{source}: expected a mapping with 'scenes', got {type(data).__name__}")
    try:
        config = RayConfig.model_validate(data)
    except ValidationError as exc:
        lines = [f"{_where(e['loc'], data) or 'config'}: {e['msg'].removeprefix('Value error, ')}"
                 for e in exc.errors()]
        raise InvalidInputError(f"{source}: " + "; ".join(lines)) from None
    for scene in config.scenes:
        for field in ("checkpoint", "replay"):
            path = getattr(scene, field)
            if path is None:
                continue
            path = path if path.is_absolute() else (base / path)
            if not path.is_file():
                raise InvalidInputError(f"{source}: scenes ({scene.name}).{field}: no file {str(path)!r}")
            setattr(scene, field, path.resolve())
    return config


def load_config(path: str | Path) -> RayConfig:
    """Read and validate the YAML config at ``path``."""
    import yaml

    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise InvalidInputError(f"cannot read the Ray config {str(path)!r}: {exc.strerror or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InvalidInputError(f"{path}: not valid YAML: {exc}") from None
    return parse_config(data, base=path.resolve().parent, source=str(path))
