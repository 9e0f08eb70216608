"""Checkpoints written behind the training: the state serialised in memory at once (a snapshot
the next steps may change behind), then the file written, synced to the disk, moved into place
and its event logged on a thread of its own.

Why: lego's thirty-minute checkpoint is 278 MB (the model and Adam's two moments). Saving it
took 1.1-1.6 s a time on a 2-core AVX2 EPYC, of which serialising 0.36-0.44 s and writing and
syncing the file 0.69-1.07 s, most of it waiting on the disk: time the training can use.

One write at a time: a new save, and ``finish``, wait for the last. A write that failed (a full
disk) is raised there, in the training's thread, with ``atomic_write``'s message; the previous
checkpoint is then still whole on disk. The thread is not a daemon: a process that ends while a
write is under way finishes it first.

Example:
    >>> import tempfile, torch
    >>> from nerf_backend.data.run_folder import RunFolder
    >>> from nerf_contract import training_events as events
    >>> run = RunFolder(tempfile.mkdtemp())
    >>> writer = CheckpointWriter(run)
    >>> writer.save({"iteration": 1, "w": torch.ones(3)}, events.Checkpoint(iteration=1, elapsed_s=0.1))
    >>> writer.finish()
    >>> run.load_checkpoint(torch.device("cpu"))["iteration"], [e.KIND for e in run.read_events()]
    (1, ['checkpoint'])
"""

from __future__ import annotations

import threading

from nerf_contract.training_events import TrainingEvent

from ..data.run_folder import RunFolder, serialised


class CheckpointWriter:
    def __init__(self, run_folder: RunFolder) -> None:
        self.run_folder = run_folder
        self._thread: threading.Thread | None = None
        self._failure: BaseException | None = None

    def save(self, state: dict, event: TrainingEvent) -> None:
        """Snapshot ``state`` now; write it and then log ``event`` behind the caller."""
        self.finish()
        buffer = serialised(state)

        def write() -> None:
            try:
                self.run_folder.write_checkpoint(buffer)
                self.run_folder.log(event)
            except BaseException as exc:  # raised again in the training's thread
                self._failure = exc

        self._thread = threading.Thread(target=write, name="checkpoint writer")
        self._thread.start()

    def finish(self) -> None:
        """Wait for the write under way, if any; raise what made it fail."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        failure, self._failure = self._failure, None
        if failure is not None:
            raise failure
