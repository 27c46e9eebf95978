"""tests/cli.py's in-process commands leave the test process as they found it."""

from __future__ import annotations

import logging
import sys

import torch

from tests.cli import run_command


class _ClosesItsStream(logging.StreamHandler):
    """Like absl's handler (made when tensorboard is imported): on close, it closes its stream unless that stream
    is ``sys.stderr`` / ``sys.stdout`` at that moment."""

    def close(self):
        if self.stream not in (sys.stderr, sys.stdout, sys.__stderr__, sys.__stdout__):
            self.stream.close()
        super().close()


def test_a_command_leaves_the_process_s_streams_handlers_and_threads(tmp_path):
    handler = _ClosesItsStream(sys.stderr)  # holds the stderr the test's capture gave it
    logging.getLogger("a.library").addHandler(handler)
    root_handlers, threads = list(logging.getLogger().handlers), torch.get_num_threads()
    try:
        # Hydra configures logging (dictConfig closes every handler), then the recipe refuses the setting
        ran = run_command(
            ["recipes/spoildice_dsrl.py", "preset=smoke", "algo.kappa=2", f"hydra.run.dir={tmp_path}"]
        )
        assert ran.returncode == 2 and "error: algo.kappa = 2" in ran.stderr
        assert not handler.stream.closed and handler.stream is sys.stderr
        print("the capture still works", file=sys.stderr)
        assert logging.getLogger().handlers == root_handlers and torch.get_num_threads() == threads
    finally:
        logging.getLogger("a.library").removeHandler(handler)
