"""What real WAMI and satellite sensors add to a rendered scene and the ground-truth simulator did not have:
motion blur, an illumination gradient, haze, a coarse grey scale and JPEG compression.

Every effect is off at its :class:`~torchtrack.sim.video_config.VideoConfig` default, and a sensor whose effects
are all off draws nothing from the generator, so a default sequence is the same as without this module. The
order follows the light: the scene is smeared by the platform's motion during the exposure (``motion_blur``: a
normalised line kernel of that length in one direction per sequence), lit unevenly (``illumination_gradient``
``g``: gain ``1 - g/2`` on one side of the frame to ``1 + g/2`` on the other, in a direction drawn per sequence)
and seen through a veil (``haze`` ``h``: ``(1 - h) I + h L`` with ``L`` the frame's 90th percentile, so contrast
falls by ``1 - h`` while the ground stays in range); the camera then adds its gain drift and noise
(:func:`torchtrack.sim.video.generate_sequence`), and :meth:`Sensor.digitise` rounds to steps of ``grey_step``
levels (a 12- or 16-bit sensor whose scene fills a small part of its range, stretched to 8 bits by its
brightest pixels) and compresses each frame as a JPEG of ``jpeg_quality``.
"""

from __future__ import annotations

import cv2
import numpy as np

from torchtrack.sim.video_config import VideoConfig


class Sensor:
    """The effects of one sequence; directions are drawn once from ``rng`` (only for effects that are on)."""

    def __init__(self, cfg: VideoConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.blur = _line_kernel(cfg.motion_blur, rng.uniform(0, np.pi)) if cfg.motion_blur > 0 else None
        self.ramp = None
        if cfg.illumination_gradient > 0:
            a = rng.uniform(0, 2 * np.pi)
            ys, xs = np.mgrid[0:cfg.height, 0:cfg.width].astype(np.float32)
            u = (xs - cfg.width / 2) * np.cos(a) + (ys - cfg.height / 2) * np.sin(a)
            self.ramp = 1 + cfg.illumination_gradient * u / max(1.0, float(np.abs(u).max()) * 2)

    def optics(self, img: np.ndarray) -> np.ndarray:
        """Motion blur, illumination gradient and haze on the float image of the scene."""
        if self.blur is not None:
            img = cv2.filter2D(img, -1, self.blur, borderType=cv2.BORDER_REFLECT)
        if self.ramp is not None:
            img = img * self.ramp
        if self.cfg.haze > 0:
            img = (1 - self.cfg.haze) * img + self.cfg.haze * np.float32(np.percentile(img, 90))
        return img

    def digitise(self, img: np.ndarray) -> np.ndarray:
        """The 8-bit frame: grey levels in steps of ``grey_step``, then JPEG compression where asked."""
        step = self.cfg.grey_step
        image = np.clip(np.rint(img / step) * step, 0, 255).astype(np.uint8)
        if self.cfg.jpeg_quality:
            ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.cfg.jpeg_quality])
            image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
        return image


def _line_kernel(length: float, angle: float) -> np.ndarray:
    """A normalised line of ``length`` px at ``angle`` (radians), anti-aliased by supersampling."""
    r = int(np.ceil(length / 2)) + 1
    kernel = np.zeros((2 * r + 1, 2 * r + 1), np.float32)
    for t in np.linspace(-length / 2, length / 2, max(2, int(8 * length) + 1)):
        x, y = r + t * np.cos(angle), r + t * np.sin(angle)
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        fx, fy = x - x0, y - y0
        kernel[y0, x0] += (1 - fx) * (1 - fy)
        kernel[y0, x0 + 1] += fx * (1 - fy)
        kernel[y0 + 1, x0] += (1 - fx) * fy
        kernel[y0 + 1, x0 + 1] += fx * fy
    return kernel / kernel.sum()
