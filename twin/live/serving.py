"""`vrscroll serve`'s service, whole: the live service (twin.live.service) made from a device profile, with the
device's morpher or the twin's, its first target, its ready line, and run until stopped with each way it can
fail as one line."""

from __future__ import annotations

import asyncio

from twin.errors import UserError
from twin.link.serial_link import LinkError
from twin.live.morph import DeviceMorpher, TwinMorpher
from twin.live.service import LiveService, ServiceConfig
from twin.morphpatch.shapes import load_mesh
from twin.records.profile import Profile


def live_service(profile: Profile, serial: str | None, log: str, tolerance_deg: float, host: str, listen: int,
                 token: str | None, allow_remote: bool, variant: str, shape: str | None = None,
                 mesh_path: str | None = None) -> LiveService:
    """The service on host:listen for the profile's twin: the device on `serial` (its session log `log`, e-stopped
    beyond tolerance_deg from the twin), or without one the twin alone; its first target a shape or a mesh file."""
    mesh = None
    if mesh_path:
        loaded = load_mesh(mesh_path)
        mesh = (loaded.vertices, loaded.faces)
    spec = profile.spec
    morpher = (DeviceMorpher(spec, serial, log, tolerance_deg, hinges=profile.hinges, mount=profile.mount) if serial
               else TwinMorpher(spec, profile.gains, hinges=profile.hinges, mount=profile.mount))
    return LiveService(ServiceConfig(spec, morpher, host=host, listen=listen, token=token, allow_remote=allow_remote,
                                     variant=variant, shape=shape, mesh=mesh, profile=profile.label))


def ready_line(service: LiveService, port: int) -> str:
    """What the service says once it listens on `port`: where, its device, its target, whether a token is asked."""
    config = service.config
    host = f"[{config.host}]" if ":" in config.host else config.host  # an IPv6 address in a URL
    return (f"vrscroll serve: listening on ws://{host}:{port} (control) and udp {host}:{port} (pose, pen); device: "
            f"{service.morpher.name}; target: {service.target['name'] if service.target else 'none'}; variant "
            f"{config.variant}" + ("; token required" if config.token else ""))


def serve_until_stopped(service: LiveService, on_loop, say=print) -> None:
    """Run the service until it stops: on_loop(loop, stop) first (e.g. the stop signals calling stop, its device
    e-stopped as it ends), say(ready_line) once it listens. UserError (one line) for the device's link or an
    address it cannot serve on."""
    async def main():
        on_loop(asyncio.get_running_loop(), service.stop)
        await service.run(lambda port: say(ready_line(service, port)))

    try:
        asyncio.run(main())
    except LinkError as exc:
        raise UserError(f"device: {exc}") from None
    except OSError as exc:
        raise UserError(f"cannot serve on {service.config.host}:{service.config.listen}: {exc}") from None
