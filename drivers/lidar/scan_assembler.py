"""Group decoded lidar packets into scans by frame id: a scan is released as soon as all its
packets are in, or, incomplete, when a packet of a later frame arrives or on flush."""

from __future__ import annotations

import numpy as np

from drivers.lidar.lidar_points import LidarPacketBatch, LidarScan

_IMAGE_FIELDS = ("range_mm", "reflectivity", "signal", "near_ir", "range2_mm")


class ScanAssembler:
    """Feed it LidarPacketBatch after LidarPacketBatch in arrival order; it returns the scans they
    complete. Packets of a frame already released are counted in `late_packets` and dropped."""

    def __init__(
        self,
        columns_per_frame: int,
        pixels_per_column: int,
        columns_per_packet: int,
        packets_per_frame: int,
        frame_id_modulus: int,
    ) -> None:
        self.columns_per_frame = columns_per_frame
        self.pixels_per_column = pixels_per_column
        self.columns_per_packet = columns_per_packet
        self.packets_per_frame = packets_per_frame  # packets a complete frame has (column window)
        self.frame_id_modulus = frame_id_modulus
        self.late_packets = 0
        self.duplicate_packets = 0
        # the frame in progress, column-major (W, H) so that each column lands in one row
        self._frame_id: int | None = None
        self._columns: dict[str, np.ndarray] = {}
        self._timestamp = np.zeros(0, np.uint64)
        self._valid = np.zeros(0, bool)
        self._received = np.zeros(0, bool)
        self._last_released: int | None = None

    def _is_after(self, frame_id: int, reference: int) -> bool:
        step = (frame_id - reference) % self.frame_id_modulus
        return 0 < step < self.frame_id_modulus // 2

    def _start(self, frame_id: int, batch: LidarPacketBatch) -> None:
        w, h = self.columns_per_frame, self.pixels_per_column
        self._frame_id = frame_id
        self._columns = {
            name: np.zeros((w, h), getattr(batch, name).dtype)
            for name in _IMAGE_FIELDS
            if getattr(batch, name) is not None
        }
        self._timestamp = np.zeros(w, np.uint64)
        self._valid = np.zeros(w, bool)
        self._received = np.zeros(w // self.columns_per_packet, bool)

    def _release(self) -> LidarScan:
        images = {name: np.ascontiguousarray(self._columns[name].T) for name in self._columns}
        scan = LidarScan(
            frame_id=self._frame_id,
            packets_received=int(np.count_nonzero(self._received)),
            packets_expected=self.packets_per_frame,
            timestamp_ns=self._timestamp,
            column_valid=self._valid,
            range_mm=images["range_mm"],
            reflectivity=images["reflectivity"],
            signal=images.get("signal"),
            near_ir=images.get("near_ir"),
            range2_mm=images.get("range2_mm"),
        )
        self._last_released = self._frame_id
        self._frame_id = None
        return scan

    def _put(self, batch: LidarPacketBatch, packets: slice) -> None:
        packet_number = batch.column_index[packets, 0] // self.columns_per_packet
        self.duplicate_packets += int(np.count_nonzero(self._received[packet_number]))
        self._received[packet_number] = True
        valid = batch.column_valid[packets]
        columns = batch.column_index[packets][valid]
        self._valid[columns] = True
        self._timestamp[columns] = batch.timestamp_ns[packets][valid]
        for name, target in self._columns.items():
            target[columns] = getattr(batch, name)[packets][valid]

    def add(self, batch: LidarPacketBatch) -> list[LidarScan]:
        released: list[LidarScan] = []
        frame_ids = batch.frame_id
        if len(frame_ids) == 0:
            return released
        starts = np.flatnonzero(np.diff(frame_ids, prepend=-1) != 0)
        ends = np.append(starts[1:], len(frame_ids))
        for start, end in zip(starts.tolist(), ends.tolist(), strict=True):
            frame_id = int(frame_ids[start])
            if self._frame_id is not None and frame_id != self._frame_id:
                if not self._is_after(frame_id, self._frame_id):
                    self.late_packets += end - start
                    continue
                released.append(self._release())
            if self._frame_id is None:
                if self._last_released is not None and not self._is_after(frame_id, self._last_released):
                    self.late_packets += end - start
                    continue
                self._start(frame_id, batch)
            self._put(batch, slice(start, end))
            if np.count_nonzero(self._received) >= self.packets_per_frame:
                released.append(self._release())
        return released

    def flush(self) -> list[LidarScan]:
        """Release the scan in progress, however incomplete."""
        return [] if self._frame_id is None else [self._release()]
