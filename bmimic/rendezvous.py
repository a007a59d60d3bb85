"""torchrun's rendezvous, met so that a rank without its peers ends in one line of its own.

torch's env:// rendezvous connects through a C++ TCP client that, while nothing listens at
MASTER_ADDR:MASTER_PORT, prints some thirty lines of C++ stack frames per retry to stderr. So the
address is resolved first, and a rank other than 0 waits in Python until rank 0 listens there; only
then does torch connect (at once). The wait runs in a daemon thread while the calling thread waits in
Python, so a stop signal is handled at once (bmimic.training.interrupts). Torch-free until torch meets.
"""

from __future__ import annotations

import datetime
import logging
import os
import socket
import threading
import time
from typing import Any

from bmimic import BmimicError

log = logging.getLogger("bmimic.runtime")

PROBE_INTERVAL_S = 0.1
"""Between two attempts of a rank other than 0 to reach rank 0's store."""


class DistributedSetupError(BmimicError):
    """torchrun's variables are malformed, or its ranks cannot meet (one line)."""


class _NotThere(Exception):
    """The address does not resolve, or nothing listened there before the deadline (the reason)."""


def wait_for_address(host: str, port: int, rank: int, deadline: float) -> None:
    """Return once `host` resolves and, for a rank other than 0, something listens at `host:port` (rank
    0's store); _NotThere with the reason at `deadline` (time.monotonic) or when `host` does not resolve."""
    try:
        socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as e:
        raise _NotThere(f"MASTER_ADDR {host!r} does not resolve: {getattr(e, 'strerror', None) or e}") from None
    if rank == 0:
        return  # rank 0 makes the store itself
    while True:
        left = deadline - time.monotonic()
        try:
            with socket.create_connection((host, port), timeout=max(0.05, min(1.0, left))):
                return
        except OSError as e:
            if time.monotonic() >= deadline:
                raise _NotThere(f"nothing listened there: {e.strerror or e}") from None
            time.sleep(PROBE_INTERVAL_S)


def meet(rank: int, world: int, timeout_s: float) -> Any:
    """torch's env:// rendezvous store of this rank (see the module doc); DistributedSetupError (one line)
    when the other ranks do not come within `timeout_s`."""
    where = f"{os.environ['MASTER_ADDR'].strip()}:{os.environ['MASTER_PORT'].strip()}"
    host, port = os.environ["MASTER_ADDR"].strip(), int(os.environ["MASTER_PORT"].strip())
    deadline = time.monotonic() + timeout_s
    result: dict[str, Any] = {}

    def run() -> None:
        try:
            wait_for_address(host, port, rank, deadline)
            import torch
            from torch.distributed.rendezvous import rendezvous as torch_rendezvous

            left = datetime.timedelta(seconds=max(1.0, deadline - time.monotonic()))
            store, _, _ = next(torch_rendezvous("env://", rank, world, timeout=left))
            store.set_timeout(torch.distributed.default_pg_timeout)
            result["store"] = store
        except Exception as e:  # noqa: BLE001 - torch raises several types (DistStoreError, ValueError, ...)
            result["error"] = e

    thread = threading.Thread(target=run, name="bmimic-rendezvous", daemon=True)
    thread.start()
    start, said = time.monotonic(), False
    while thread.is_alive():
        thread.join(0.2)
        waited = time.monotonic() - start
        if not said and waited > 5 and thread.is_alive():
            log.info("torchrun: rank %d of %d waiting for the other ranks at %s (up to %g s)", rank, world, where,
                     timeout_s)
            said = True
        if waited > timeout_s + 30:  # torch's own timeout should have ended it by now
            break
    if "store" in result:
        return result["store"]
    error = result.get("error")
    detail = str(error).strip().splitlines()[0] if error is not None and str(error).strip() else "no answer"
    raise DistributedSetupError(
        f"torchrun: rank {rank} of {world} could not meet the other ranks at MASTER_ADDR:MASTER_PORT={where} within "
        f"{timeout_s:g} s ({detail[:200]}); start every rank (torchrun --nproc-per-node {world}), or unset "
        "WORLD_SIZE and RANK to run one process ($BMIMIC_RENDEZVOUS_TIMEOUT_S sets the wait)")


__all__ = ["DistributedSetupError", "meet", "wait_for_address"]
