"""The corner detector's jobs: `envisat train` (shards or online rendering: the render pool, the device pool, the mix of looks), `envisat detect`, `envisat evaluate` and `envisat calibrate`."""
