"""Group decoded lidar packets into scans by frame id: a scan is released as soon as all its
packets are in, or, incomplete, when a packet of a later frame arrives or on flush."""

from __future__ import annotations

import numpy as np

from drivers.lidar.lidar_points import LidarPacketBatch, LidarScan


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
        self._scan: LidarScan | None = None
        self._received: np.ndarray = np.zeros(0, bool)
        self._last_released: int | None = None

    def _is_after(self, frame_id: int, reference: int) -> bool:
        step = (frame_id - reference) % self.frame_id_modulus
        return 0 < step < self.frame_id_modulus // 2

    def _start(self, frame_id: int, batch: LidarPacketBatch) -> None:
        h, w = self.pixels_per_column, self.columns_per_frame

        def image(source: np.ndarray | None, dtype) -> np.ndarray | None:
            return None if source is None else np.zeros((h, w), dtype)

        self._scan = LidarScan(
            frame_id=frame_id,
            packets_received=0,
            packets_expected=self.packets_per_frame,
            timestamp_ns=np.zeros(w, np.uint64),
            column_valid=np.zeros(w, bool),
            range_mm=np.zeros((h, w), np.uint32),
            reflectivity=np.zeros((h, w), np.uint8),
            signal=image(batch.signal, np.uint16),
            near_ir=image(batch.near_ir, np.uint16),
            range2_mm=image(batch.range2_mm, np.uint32),
        )
        self._received = np.zeros(w // self.columns_per_packet, bool)

    def _release(self) -> LidarScan:
        scan = self._scan
        self._last_released = scan.frame_id
        self._scan = None
        return scan

    def _put(self, batch: LidarPacketBatch, packets: slice) -> None:
        scan = self._scan
        packet_number = batch.column_index[packets, 0] // self.columns_per_packet
        fresh = ~self._received[packet_number]
        self.duplicate_packets += int(np.count_nonzero(~fresh))
        self._received[packet_number] = True
        scan.packets_received = int(np.count_nonzero(self._received))
        valid = batch.column_valid[packets]
        columns = batch.column_index[packets][valid]
        scan.column_valid[columns] = True
        scan.timestamp_ns[columns] = batch.timestamp_ns[packets][valid]
        for name in ("range_mm", "reflectivity", "signal", "near_ir", "range2_mm"):
            target = getattr(scan, name)
            if target is not None:
                target[:, columns] = getattr(batch, name)[packets][valid].T

    def add(self, batch: LidarPacketBatch) -> list[LidarScan]:
        released: list[LidarScan] = []
        frame_ids = batch.frame_id
        if len(frame_ids) == 0:
            return released
        starts = np.flatnonzero(np.diff(frame_ids, prepend=-1) != 0)
        ends = np.append(starts[1:], len(frame_ids))
        for start, end in zip(starts.tolist(), ends.tolist(), strict=True):
            frame_id = int(frame_ids[start])
            if self._scan is not None and frame_id != self._scan.frame_id:
                if not self._is_after(frame_id, self._scan.frame_id):
                    self.late_packets += end - start
                    continue
                released.append(self._release())
            if self._scan is None:
                if self._last_released is not None and not self._is_after(frame_id, self._last_released):
                    self.late_packets += end - start
                    continue
                self._start(frame_id, batch)
            self._put(batch, slice(start, end))
            if self._scan.packets_received >= self.packets_per_frame:
                released.append(self._release())
        return released

    def flush(self) -> list[LidarScan]:
        """Release the scan in progress, however incomplete."""
        return [] if self._scan is None else [self._release()]
