"""Whether the car's rings can work, checked before the daemon makes them (and by `roadlog check-config`): each ring
holds a few of its topic's largest messages, and all of them fit in /dev/shm (Docker's default /dev/shm is 64 MiB;
the default rings of a three-camera car need ~480 MiB). Each ring's pages are also reserved when it is made
(ring_layout.reserve_space), so a /dev/shm that another program fills later cannot SIGBUS a writer mid-drive.

Setting ROADLOG_SIMULATED_SHM_BYTES makes the check see an empty /dev/shm of that size, so tests can try a small one.
"""

from __future__ import annotations

import glob
import os

from daemon.bus.ring_layout import DATA_OFFSET, PAGE, record_bytes
from daemon.spine.config import CarConfig, ConfigError
from daemon.spine.topics import topic_table

SHM_DIR = "/dev/shm"
SIMULATED_SHM_ENV = "ROADLOG_SIMULATED_SHM_BYTES"
MESSAGES_PER_RING = 2  # the fewest of its largest messages a ring must hold (one being read while one is written)
META_BYTES = 1024  # room for a message's encoded metadata beside its payload
MIB = 1024 * 1024


def ring_file_bytes(ring_bytes: int) -> int:
    """What a ring of `ring_bytes` takes in /dev/shm once written through: its header pages and its data area."""
    return DATA_OFFSET + max(0, ring_bytes)


def smallest_ring(max_message_bytes: int) -> int:
    """The smallest ring that holds MESSAGES_PER_RING messages of that payload size."""
    return max(PAGE, MESSAGES_PER_RING * record_bytes(META_BYTES, max_message_bytes))


def shm_space(prefix: str) -> tuple[int, int]:
    """(size, free) of /dev/shm in bytes, counting this bus's own rings as free (the daemon makes them afresh)."""
    simulated = os.environ.get(SIMULATED_SHM_ENV)
    if simulated:
        return int(simulated), int(simulated)
    st = os.statvfs(SHM_DIR)
    ours = 0
    for path in glob.glob(os.path.join(SHM_DIR, f"{prefix}.*")):
        try:
            ours += os.stat(path).st_blocks * 512
        except FileNotFoundError:
            continue
    return st.f_blocks * st.f_frsize, st.f_bavail * st.f_frsize + ours


def check_rings(config: CarConfig, config_path: str | None = None) -> None:
    """ConfigError naming every ring too small for its topic's messages, and /dev/shm when the rings outgrow it."""
    table = topic_table(config)  # names an unknown topic in bus.ring_bytes
    problems = []
    for name, topic in sorted(table.items()):
        least = smallest_ring(topic.max_message_bytes)
        if topic.ring_bytes < least:
            setting = f"bus.ring_bytes[{name!r}] = {topic.ring_bytes}" if name in config.bus.ring_bytes else \
                f"the ring of {name!r} ({topic.ring_bytes} B)"
            problems.append(f"{setting} cannot hold {MESSAGES_PER_RING} of its {topic.max_message_bytes} B "
                            f"messages: at least {least} B")
    needed = sum(ring_file_bytes(t.ring_bytes) for t in table.values())
    size, free = shm_space(config.bus.shm_prefix)
    hint = ("enlarge /dev/shm (Docker: --shm-size; systemd: a larger tmpfs) or lower bus.ring_bytes "
            "(per topic, see daemon/spine/topics.py)")
    if needed > size:
        problems.append(f"the {len(table)} rings need {needed / MIB:.0f} MiB of {SHM_DIR}, which holds "
                        f"{size / MIB:.0f} MiB: {hint}")
    elif needed > free:
        problems.append(f"the {len(table)} rings need {needed / MIB:.0f} MiB of {SHM_DIR}, which has "
                        f"{free / MIB:.0f} MiB free of {size / MIB:.0f} MiB: {hint}")
    if problems:
        where = f"{config_path}: " if config_path else ""
        raise ConfigError(where + "; ".join(problems))
