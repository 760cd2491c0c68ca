"""A camera's response: how the light a pixel collected becomes the number its file stores.

A raw or scientific camera stores a value proportional to the light (`linear`); most cameras' JPEG files and most
renderers' PNG files store it encoded by the sRGB curve (`srgb`: 12.92 v below 0.0031308, 1.055 v^(1/2.4) - 0.055
above, IEC 61966-2-1) or by a plain power (`gamma` g: v^(1/g)). Values are relative to white: light 1 is stored as
1 (255 in 8 bits). Blur acts on light, so an edge blurred by a symmetric PSF is antisymmetric about its midpoint
only in linear light: encoded after the blur, a bright body's edge on a dark sky reads outward.

Pure functions of NumPy arrays; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envisat_pose.config import check

RESPONSE_KINDS = ("linear", "srgb", "gamma")
GAMMA_RANGE = (0.5, 4.0)  # a power outside it is no camera's response (a typo, or a contrast curve)
SRGB_KNEE = 0.0031308     # linear light where the sRGB curve turns from its line to its power


@dataclass(frozen=True)
class Response:
    """kind: 'linear', 'srgb' or 'gamma'; gamma: the power g of 'gamma' (stored = light^(1/g)); 1 otherwise."""

    kind: str = "linear"
    gamma: float = 1.0

    def __post_init__(self) -> None:
        check(self.kind in RESPONSE_KINDS, "response", self.kind, "'linear', 'srgb' or a gamma")
        if self.kind == "gamma":
            check(GAMMA_RANGE[0] <= self.gamma <= GAMMA_RANGE[1], "response.gamma", self.gamma,
                  f"a power in [{GAMMA_RANGE[0]:g}, {GAMMA_RANGE[1]:g}]")
        else:
            check(self.gamma == 1.0, "response.gamma", self.gamma, f"1 for the {self.kind!r} response")

    @property
    def is_linear(self) -> bool:
        return self.kind == "linear" or (self.kind == "gamma" and self.gamma == 1.0)

    def name(self) -> str:
        """'linear', 'srgb' or 'gamma 2.2': as a report or a camera file writes it."""
        return f"gamma {self.gamma:g}" if self.kind == "gamma" else self.kind

    def encode(self, light: np.ndarray) -> np.ndarray:
        """Stored value (0-1) of light (0-1, relative to white), float64."""
        v = np.clip(np.asarray(light, dtype=np.float64), 0.0, 1.0)
        if self.kind == "srgb":
            return np.where(v <= SRGB_KNEE, 12.92 * v, 1.055 * v ** (1.0 / 2.4) - 0.055)
        if self.kind == "gamma":
            return v ** (1.0 / self.gamma)
        return v

    def decode(self, stored: np.ndarray) -> np.ndarray:
        """Light (0-1) of a stored value (0-1): encode's inverse, float64."""
        v = np.clip(np.asarray(stored, dtype=np.float64), 0.0, 1.0)
        if self.kind == "srgb":
            return np.where(v <= 12.92 * SRGB_KNEE, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
        if self.kind == "gamma":
            return v ** self.gamma
        return v

    def linear_lut(self) -> np.ndarray:
        """The light of each 8-bit value, in grey levels of white 255: (256,) float32."""
        return (255.0 * self.decode(np.arange(256) / 255.0)).astype(np.float32)

    def encode_lut(self) -> np.ndarray:
        """The 8-bit stored value of each 8-bit linear value (rounded): (256,) uint8."""
        return np.rint(255.0 * self.encode(np.arange(256) / 255.0)).astype(np.uint8)

    def linearize(self, image_u8: np.ndarray) -> np.ndarray:
        """An 8-bit image (any shape) as light in grey levels of white 255: float32 (the image itself, as float32,
        for a linear response)."""
        if self.is_linear:
            return np.asarray(image_u8, dtype=np.float32)
        return self.linear_lut()[np.asarray(image_u8, dtype=np.uint8)]


LINEAR = Response()
SRGB = Response("srgb")


def parse_response(value, field: str) -> Response:
    """A response from a config or camera file value: 'linear', 'srgb', a number g (a gamma; 1 is linear) or
    'gamma G'. InputError-style (config.check) naming `field` otherwise."""
    if isinstance(value, bool):
        check(False, field, value, "'linear', 'srgb' or a gamma (a number)")
    if isinstance(value, (int, float)):
        check(np.isfinite(value), field, value, "a finite gamma")
        return LINEAR if float(value) == 1.0 else Response("gamma", float(value))
    text = str(value).strip().lower()
    if text in ("linear", "srgb"):
        return Response(text)
    parts = text.split()
    if len(parts) == 2 and parts[0] == "gamma":
        try:
            return parse_response(float(parts[1]), field)
        except ValueError:
            pass
    check(False, field, value, "'linear', 'srgb' or a gamma (a number, or 'gamma 2.2')")
    raise AssertionError  # check raised
