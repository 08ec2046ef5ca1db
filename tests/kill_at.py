"""Run the pomil command line and SIGKILL this process at a chosen point (the resume tests).

    python tests/kill_at.py checkpoint N ARGS...   killed right after the checkpoint of iteration N is written
    python tests/kill_at.py log N ARGS...          killed as iteration N's row is logged, before its checkpoint
    python tests/kill_at.py never 0 ARGS...        not killed: the uninterrupted run, in a process like the others

A kill -9 leaves no chance to clean up: the run's lock stays, its log has rows past the checkpoint, and
whatever the process held in memory is gone; ``--resume`` must go on from the checkpoint as if nothing happened.
"""

import os
import signal
import sys

import pomil.training as training
from pomil.cli import main


def _kill() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


if __name__ == "__main__":
    point, at, args = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
    if point == "checkpoint":
        save = training.save_run_checkpoint

        def save_then_kill(path, logger, guard, *, iteration, payload):
            save(path, logger, guard, iteration=iteration, payload=payload)
            if iteration == at:
                _kill()
        training.save_run_checkpoint = save_then_kill
    elif point == "log":
        log = training.RunLogger.log

        def log_then_kill(self, iteration, stats):
            log(self, iteration, stats)
            if iteration == at:
                self.flush()  # the row reaches the file, as a later flush would have written it before the kill
                _kill()
        training.RunLogger.log = log_then_kill
    elif point != "never":
        raise SystemExit(f"kill_at.py: unknown point {point!r}")
    sys.exit(main(args))
