"""This process's renderers (shared_renderer): one SceneRenderer per resolution, shadows, texture set, Earth
texture seed and target, created on first use and reused (one per worker: a GL context costs 0.1-0.3 s), all
freed before the GL library unloads at exit (close_renderers)."""

from __future__ import annotations

from envisat_pose.datagen.render import SceneRenderer
from envisat_pose.target import DEFAULT_TARGET, load_target

_RENDERERS: dict[tuple, SceneRenderer] = {}


def shared_renderer(resolution_px: int, shadows: bool = True, texture_set_size: int = 0,
                    texture_seed: int = 0, earth_seed: int = 0, target: str = DEFAULT_TARGET) -> SceneRenderer:
    """This process's renderer for (resolution, shadows, texture set, Earth texture seed, target file and its
    sha256), created on first use and reused (one per worker)."""
    key = (int(resolution_px), bool(shadows), int(texture_set_size), int(texture_seed), int(earth_seed), target,
           load_target(target).sha256)
    if key not in _RENDERERS:
        first = not _RENDERERS
        _RENDERERS[key] = SceneRenderer(resolution_px, shadows, texture_set_size=texture_set_size,
                                        texture_seed=texture_seed, earth_seed=earth_seed, target=target)
        if first:
            import atexit

            # registered after the GL platform module's own exit hook (EGL terminates its display there):
            # exit hooks run last-in first-out, so the renderers are freed while the display still exists
            atexit.register(close_renderers)
    return _RENDERERS[key]


def close_renderers() -> None:
    """Free every cached renderer of this process (before the GL library unloads at exit)."""
    while _RENDERERS:
        _, r = _RENDERERS.popitem()
        r.close()
