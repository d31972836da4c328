"""The mapper's optional Foxglove live view (`mapper.live_view.enabled`): a Foxglove WebSocket server
(foxglove-sdk, the `live-view` extra) on which each finished window publishes its map.

Topics, all in frame `map` (the worker's ENU frame), stamped with the window's end on the host clock:
- `/map/bev_rgb`, `/map/bev_semantics`, `/map/bev_elevation` (foxglove.CompressedImage, PNG, north up):
  the window's bird's-eye views, as the status endpoint's previews;
- `/map/elevation` (foxglove.Grid): the window's elevation raster (float32 `elevation` field, NaN =
  unmapped), placed at its ENU origin, so the 3D panel shows the surface growing window by window;
- `/map/trajectory` (foxglove.PosesInFrame): the window's trajectory.
Foxglove Studio connects to ws://HOST:PORT. The server has its own context: nothing else the process
logs through foxglove reaches it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from daemon.spine.mapper_config import LiveViewConfig
from mapping.live.map_images import north_up_png

FRAME = "map"


@dataclass
class LiveView:
    context: object  # foxglove.Context: held, or its channels leave the server
    server: object  # foxglove.WebSocketServer
    channels: dict[str, object]
    published: int = 0

    @property
    def port(self) -> int:
        return self.server.port


def start_live_view(config: LiveViewConfig, name: str = "roadlog mapper") -> LiveView:
    """Start the WebSocket server and advertise the map's channels."""
    import foxglove
    from foxglove.channels import CompressedImageChannel, GridChannel, PosesInFrameChannel

    context = foxglove.Context()
    channels = {topic: CompressedImageChannel(topic, context=context)
                for topic in ("/map/bev_rgb", "/map/bev_semantics", "/map/bev_elevation")}
    channels["/map/elevation"] = GridChannel("/map/elevation", context=context)
    channels["/map/trajectory"] = PosesInFrameChannel("/map/trajectory", context=context)
    server = foxglove.start_server(name=name, host=config.bind_address, port=config.port, context=context)
    return LiveView(context, server, channels)


def publish_window(view: LiveView, stamp_ns: int, images: dict[str, np.ndarray], elevation: np.ndarray,
                   origin_xy: tuple[float, float], resolution_m: float, trajectory_xyz: np.ndarray) -> None:
    """Publish one finished window: `images` maps "rgb"/"semantics"/"elevation" to (H, W, 3) uint8 BEVs;
    `elevation` is the (H, W) raster whose cell (i, j) is centred at origin + (j, i) * resolution."""
    from foxglove.messages import (
        CompressedImage,
        Grid,
        PackedElementField,
        PackedElementFieldNumericType,
        Pose,
        PosesInFrame,
        Quaternion,
        Timestamp,
        Vector2,
        Vector3,
    )

    stamp = Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)
    for name, rgb in images.items():
        png = north_up_png(rgb, "a live-view image")
        view.channels[f"/map/bev_{name}"].log(CompressedImage(timestamp=stamp, frame_id=FRAME, data=png,
                                                              format="png"), log_time=stamp_ns)
    h, w = elevation.shape
    corner = Pose(position=Vector3(x=origin_xy[0] - resolution_m / 2, y=origin_xy[1] - resolution_m / 2, z=0.0),
                  orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
    grid = Grid(timestamp=stamp, frame_id=FRAME, pose=corner, column_count=w,
                cell_size=Vector2(x=resolution_m, y=resolution_m), row_stride=4 * w, cell_stride=4,
                fields=[PackedElementField(name="elevation", offset=0, type=PackedElementFieldNumericType.Float32)],
                data=np.ascontiguousarray(elevation, np.float32).tobytes())
    view.channels["/map/elevation"].log(grid, log_time=stamp_ns)
    poses = [Pose(position=Vector3(x=float(x), y=float(y), z=float(z)),
                  orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)) for x, y, z in trajectory_xyz]
    view.channels["/map/trajectory"].log(PosesInFrame(timestamp=stamp, frame_id=FRAME, poses=poses),
                                         log_time=stamp_ns)
    view.published += 1


def stop_live_view(view: LiveView) -> None:
    view.server.stop()
