"""The trainer's device pool of online training (pipelines/detector/online.py): the current window's frames on the torch
device, loaded from the renderer processes (pipelines/detector/render_pool.py) through pinned host buffers on CUDA."""

from __future__ import annotations

from envisat_pose.pipelines.detector.render_pool import RenderPool


class DevicePool:
    """The window's frames on the device, frame f in slot f mod N: frames (N, H, W) uint8, corners_px (N, K, 2)
    float64 (K keypoints a frame: 8, ENVISAT's corners), visible and in_frame (N, K) bool, frame (N,) int64, hw
    (N, 2) int64 (each frame's own size). New frames go through a pinned host buffer on CUDA (copied without
    waiting for the device; two buffers in turn, each reused after its copy is done)."""

    def __init__(self, n: int, res: int, device, keypoints: int = 8):
        import torch

        self.n, self.device = n, device
        self.frames = torch.zeros((n, res, res), dtype=torch.uint8, device=device)
        self.corners_px = torch.zeros((n, keypoints, 2), dtype=torch.float64, device=device)
        self.visible = torch.zeros((n, keypoints), dtype=torch.bool, device=device)
        self.in_frame = torch.zeros((n, keypoints), dtype=torch.bool, device=device)
        self.frame = torch.full((n,), -1, dtype=torch.int64, device=device)
        self.hw = torch.full((n, 2), res, dtype=torch.int64, device=device)
        cuda = device.type == "cuda"
        self.staging = [self._host(n, res, keypoints, cuda) for _ in range(2 if cuda else 1)]
        self.events = [None] * len(self.staging)
        self.turn = 0

    @staticmethod
    def _host(n: int, res: int, k: int, pinned: bool) -> dict:
        import torch

        def t(shape, dtype):
            return torch.zeros(shape, dtype=dtype, pin_memory=pinned)

        return {"frames": t((n, res, res), torch.uint8), "corners_px": t((n, k, 2), torch.float64),
                "visible": t((n, k), torch.bool), "in_frame": t((n, k), torch.bool), "frame": t((n,), torch.int64),
                "hw": t((n, 2), torch.int64)}

    def load(self, source: RenderPool, count: int) -> None:
        """Take the next `count` frames from source into their slots."""
        import torch

        if count <= 0:
            return
        k = self.turn
        self.turn = (self.turn + 1) % len(self.staging)
        if self.events[k] is not None:
            self.events[k].synchronize()  # the buffer's last copy is done
        host = self.staging[k]
        images = host["frames"].numpy()
        for i in range(count):
            frame, corners, visible, in_frame, side = source.take(images[i])
            host["corners_px"][i] = torch.from_numpy(corners)
            host["visible"][i] = torch.from_numpy(visible)
            host["in_frame"][i] = torch.from_numpy(in_frame)
            host["frame"][i] = frame
            host["hw"][i] = side
        slots = (host["frame"][:count] % self.n).to(self.device)
        blocking = self.device.type != "cuda"
        for name in ("frames", "corners_px", "visible", "in_frame", "frame", "hw"):
            getattr(self, name).index_copy_(0, slots, host[name][:count].to(self.device, non_blocking=not blocking))
        if not blocking:
            self.events[k] = torch.cuda.Event()
            self.events[k].record()
