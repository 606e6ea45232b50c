"""Memory a sample needs, estimated before any work, so a size that cannot fit is refused up front.

Without this, ``--width 100000 --height 100000`` ends in Warp's out-of-memory traceback after the
export folder was created. The estimate is linear in pixels x frames:

    bytes(sample) = BASE_BYTES + BYTES_PER_PIXEL_FRAME * width * height * num_frames

Measured peak resident memory (``/usr/bin/time -f %M``, ``flowsynth export --num 1 --num-frames 8`` with
the default outputs): 0.84 GiB at 320x240 and 1.63 GiB at 640x480, i.e. ~450 B per pixel and frame on
top of ~0.6 GiB for the interpreter, torch, Warp and Newton. The constants round both up a little;
a third size checks them: 480x360, 16 frames predicts 1906 MiB and peaked at 1837 MiB.
"""

from __future__ import annotations

import os

from flowsynth.errors import ConfigError

__all__ = ["BASE_BYTES", "BYTES_PER_PIXEL_FRAME", "available_memory_bytes", "cgroup_room_bytes",
           "check_sample_memory", "sample_memory_bytes"]

BYTES_PER_PIXEL_FRAME = 480
"""Peak memory per pixel and frame of one sample [bytes] (measured ~450, see the module docstring)."""
BASE_BYTES = 640 << 20
"""Memory of one generating process before any pixel [bytes] (measured ~0.6 GiB = 615 MiB)."""
_GIB = float(1 << 30)


def sample_memory_bytes(cfg) -> int:
    """Estimated peak memory [bytes] of one process generating one sample of ``cfg``."""
    return BASE_BYTES + BYTES_PER_PIXEL_FRAME * cfg.width * cfg.height * cfg.num_frames


def _system_available() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def cgroup_room_bytes(root: str = "/sys/fs/cgroup") -> int | None:
    """Memory this process's cgroup (v2) may still take [bytes]: its ``memory.max`` less what it holds beyond
    reclaimable file pages (``memory.current`` less ``file`` of ``memory.stat``); None without a limit or a
    cgroup v2 (a container's memory limit is one)."""
    try:
        with open("/proc/self/cgroup") as f:
            path = next(line.split(":", 2)[2].strip() for line in f if line.startswith("0::"))
        folder = os.path.join(root, path.lstrip("/"))
        with open(os.path.join(folder, "memory.max")) as f:
            limit = f.read().strip()
        if limit == "max":
            return None
        with open(os.path.join(folder, "memory.current")) as f:
            current = int(f.read())
        with open(os.path.join(folder, "memory.stat")) as f:
            file = next((int(line.split()[1]) for line in f if line.startswith("file ")), 0)
        return max(int(limit) - (current - file), 0)
    except (OSError, ValueError, IndexError, StopIteration):
        return None


def available_memory_bytes() -> int | None:
    """Memory this process may use without swapping [bytes]: the system's (``MemAvailable`` of /proc/meminfo, else
    free pages from ``os.sysconf``), or its cgroup's room (``cgroup_room_bytes``) where that is less; None where
    neither is known."""
    known = [m for m in (_system_available(), cgroup_room_bytes()) if m is not None]
    return min(known) if known else None


def check_sample_memory(cfg, processes: int = 1) -> None:
    """Raise ConfigError naming the size flags and the estimate in GiB when ``processes`` processes
    generating samples of ``cfg`` at once would need more memory than is available."""
    need = sample_memory_bytes(cfg) * processes
    avail = available_memory_bytes()
    if avail is None or need <= avail:
        return
    each = sample_memory_bytes(cfg) / _GIB
    who = f"{processes} worker processes need {need / _GIB:.1f} GiB" if processes > 1 else "that is"
    raise ConfigError(
        f"--width {cfg.width} --height {cfg.height} --num-frames {cfg.num_frames}: one sample needs about "
        f"{each:.1f} GiB of memory (estimate), {who}, but only {avail / _GIB:.1f} GiB are available; lower "
        f"--width/--height/--num-frames" + (" or --workers" if processes > 1 else ""))
