"""Uploading the next batch while the current one trains.

On CUDA, ``DevicePrefetcher`` copies batch k+1 to the GPU (and normalises its images,
batch.to_device) on a side stream while the step of batch k runs on the current stream:
the copy engine and the compute overlap, and the host has queued the next upload before it
queues the next step. Two rules make this safe:
- the current stream waits for an event recorded after batch k's upload (not for the whole
  side stream, which by then holds batch k+1's copies too);
- every device tensor of batch k is marked as used by the current stream
  (``record_stream``), so the caching allocator does not give its memory to a later upload
  while the step still reads it. The host keys (batch.HOST_KEYS) stay on the host.
Elsewhere it uploads batch by batch, fetching nothing ahead: on the CPU the loader is read
exactly when it was before (a resumed run's random draws stay where they were). On CUDA with
``workers=0`` the look-ahead loads a sample before the step ahead of it, so the history
intervals are drawn in another order than without it (a CUDA run is not bit-exact anyway).
"""
from __future__ import annotations

import torch

from .batch import HOST_KEYS, tensors_in, to_device


class CudaStreams:
    """The CUDA stream calls of the prefetcher, in one place (a test records them instead)."""

    def __init__(self, device: torch.device):
        self.current = torch.cuda.current_stream(device)
        self.side = torch.cuda.Stream(device)

    def on_side(self):
        return torch.cuda.stream(self.side)

    def mark_uploaded(self):
        event = torch.cuda.Event()
        event.record(self.side)
        return event

    def wait(self, event) -> None:
        self.current.wait_event(event)

    def keep_for_current(self, tensor: torch.Tensor) -> None:
        tensor.record_stream(self.current)


def batch_tensors(batch: dict):
    """The batch's tensors on the device: the host keys stay on the host (batch.to_device),
    where there is no stream to keep them for."""
    for key, value in batch.items():
        if key not in HOST_KEYS:
            yield from tensors_in(value)


class DevicePrefetcher:
    """Iterates over host batches, yielding them on ``device`` (module docstring).
    ``streams``: a CudaStreams, or a stand-in with its methods (tests); made on CUDA."""

    def __init__(self, batches, device, upload=to_device, streams=None):
        self.batches, self.device, self.upload = batches, torch.device(device), upload
        self.streams = streams

    def __iter__(self):
        streams = self.streams
        if streams is None and self.device.type == "cuda":
            streams = CudaStreams(self.device)
        if streams is None:
            for batch in self.batches:
                yield self.upload(batch, self.device)
            return
        staged = None
        for host in self.batches:
            with streams.on_side():
                uploaded = self.upload(host, self.device)
                event = streams.mark_uploaded()
            if staged is not None:
                yield self._hand_over(streams, *staged)
            staged = uploaded, event
        if staged is not None:
            yield self._hand_over(streams, *staged)

    @staticmethod
    def _hand_over(streams, batch: dict, event) -> dict:
        streams.wait(event)
        for tensor in batch_tensors(batch):
            streams.keep_for_current(tensor)
        return batch
