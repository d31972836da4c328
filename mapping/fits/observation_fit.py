"""The fast path's optimisation: the EMIE-MAP model fitted to per-vertex observations instead of to
rendered pixels, with the paper's losses taken per vertex.

- Elevation: the residual MLP is fitted with the L1 Lidar loss and the smoothness loss on the lattice
  it is evaluated on (`lattice_m`): every lattice node with Lidar ground points nearby takes their mean
  residual over z0 as its target, the whole drive at once (the elevation is low-frequency, the Lidar
  dense), in minibatches of nodes, with a cosine learning-rate decay (the fit is short: without it the
  result swung with the seed by more than the curbs' detail).
- Semantics: the cross-entropy summed over a vertex's observed labels is minimised by the log of its
  label frequencies, which is where the explicit logits are set (with a small prior), the lane marking's
  raised on the centres of lines the views blurred (mapping.fits.lane_line_centres).
- Colour: the per-vertex codes and the per-camera decoders are fitted with the L1 colour loss to the
  mean colour each camera saw at each vertex. The codes come from a small encoder of those colours,
  trained jointly with the decoders on samples of vertices, then applied to every vertex. (Refining every
  code afterwards with full-batch steps at the paper's code learning rate barely moved held-out PSNR at a
  high cost a step, and lost PSNR at higher rates: it was removed.)
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from daemon.spine.semantic_classes import SemanticClass
from mapping.fits.lane_line_centres import raise_line_centres
from mapping.fits.vertex_observations import VertexObservations
from mapping.method.adam import Adam, CosineDecay
from mapping.method.compute_device import optimisation_loop
from mapping.method.descent import Descent
from mapping.method.mesh_location import Located
from mapping.method.road_map import RoadMap

LABEL_PRIOR = 0.1
FINAL_LR_FRACTION = 0.05  # the elevation fit's learning rate ends at 5 % of the paper's
_KEY = 1 << 21
_CPU = torch.device("cpu")  # where the road map lives between the fits (the evaluation and the exports read it)


def semantic_logits_from_counts(counts: np.ndarray, neighbours: np.ndarray | None = None,
                                line_gain: float = 0.0) -> torch.Tensor:
    """Log label frequencies (with a small prior) of (M, C) label counts. With the mesh's `neighbours` (M, 6) (the
    counts then of every vertex, a row of zeros where nothing was read), the lane marking's frequency is raised on
    line centres by `line_gain` (mapping.fits.lane_line_centres)."""
    total = counts.sum(1, keepdims=True)
    p = (counts + LABEL_PRIOR) / (total + LABEL_PRIOR * counts.shape[1])
    if neighbours is not None:
        p = raise_line_centres(p, neighbours, total[:, 0] > 0, SemanticClass.LANE_MARKING, line_gain)
    return torch.from_numpy(np.log(p).astype(np.float32))


def lidar_lattice_targets(road_map: RoadMap, points: np.ndarray, located: Located, lattice_m: float):
    """Lattice nodes (K, 2 int) with Lidar ground points nearby, their mean residual target over z0 (K,),
    their mean z0 (K,) and their point counts (K,). `located`: the points placed on the mesh."""
    ok = located.inside
    ids, w, p = located.ids[ok], located.weights[ok], points[ok]
    z0 = (road_map.mesh.z0[ids] * w).sum(1)
    local = p[:, :2] - np.asarray(road_map.elevation.origin_xy)
    node = np.rint(local / lattice_m).astype(np.int64)
    key = (node[:, 0] + _KEY // 2) * _KEY + (node[:, 1] + _KEY // 2)
    unique, inverse, count = np.unique(key, return_inverse=True, return_counts=True)
    target = np.bincount(inverse, weights=p[:, 2] - z0) / count
    z0_node = np.bincount(inverse, weights=z0) / count
    nodes = np.stack([unique // _KEY - _KEY // 2, unique % _KEY - _KEY // 2], 1)
    return nodes, target.astype(np.float32), z0_node.astype(np.float32), count


def _lattice_edges(nodes: np.ndarray) -> np.ndarray:
    """(E, 2) index pairs of 4-adjacent nodes among `nodes`."""
    key = (nodes[:, 0] + _KEY // 2) * _KEY + (nodes[:, 1] + _KEY // 2)
    order = np.argsort(key)
    out = []
    for step in (_KEY, 1):  # +1 in x, +1 in y
        pos = np.searchsorted(key[order], key + step)
        pos = np.minimum(pos, len(key) - 1)
        hit = key[order][pos] == key + step
        out.append(np.stack([np.nonzero(hit)[0], order[pos[hit]]], 1))
    return np.concatenate(out)


def step_bar(steps: int, what: str, shown: bool) -> tqdm:
    """A fit's progress bar (steps, rate, ETA) on stderr, or a silent one."""
    return tqdm(total=steps, desc=what, unit="step", disable=not shown, mininterval=0.5)


def fit_elevation(road_map: RoadMap, points: np.ndarray, located: Located, lattice_m: float, epochs: float,
                  min_steps: int, batch: int, smooth_pairs: int, lr: float, w_elevation: float, w_smooth: float,
                  rng: np.random.Generator, device: torch.device = _CPU, progress: bool = False
                  ) -> tuple[float, float]:
    """Fit the residual MLP to the Lidar ground points (L1; `located`: the points placed on the mesh) with
    lattice smoothness (fit_lattice, on `device`); returns the weighted loss of the first and the last step."""
    nodes, target, z0, _ = lidar_lattice_targets(road_map, points, located, lattice_m)
    return fit_lattice(road_map, nodes, target, z0, None, lattice_m, epochs, min_steps, batch, smooth_pairs, lr,
                       w_elevation, w_smooth, rng, device, progress)


def fit_lattice(road_map: RoadMap, nodes: np.ndarray, target: np.ndarray, z0: np.ndarray,
                weight: np.ndarray | None, lattice_m: float, epochs: float, min_steps: int, batch: int,
                smooth_pairs: int, lr: float, w_elevation: float, w_smooth: float,
                rng: np.random.Generator, device: torch.device = _CPU, progress: bool = False
                ) -> tuple[float, float]:
    """Fit the residual MLP to residual targets `target` at lattice nodes `nodes` (K, 2) (their z0 `z0`) by L1,
    weighted per node by `weight` (None: all alike; a node of weight 0 takes part in the smoothness only), with
    lattice smoothness, `epochs` passes over the nodes in minibatches of `batch` nodes and `smooth_pairs`
    neighbour pairs (at least `min_steps` steps), the learning rate decaying from `lr` to 5 % of it along a
    cosine; returns the weighted loss of the first and the last step. The MLP and the lattice go to `device` once
    (every step's draws too, drawn before the loop in the order the steps take them), the MLP comes back after.
    `progress`: a bar of the steps with its ETA on stderr."""
    steps = max(min_steps, int(np.ceil(epochs * len(nodes) / batch)))
    edges = _lattice_edges(nodes)
    draws = [(rng.choice(len(nodes), batch, replace=False) if len(nodes) > batch else np.arange(len(nodes)),
              rng.choice(len(edges), smooth_pairs, replace=False) if len(edges) > smooth_pairs
              else np.arange(len(edges))) for _ in range(steps)]
    picks = torch.from_numpy(np.stack([pick for pick, _ in draws])).to(device)
    pairs = torch.from_numpy(np.stack([edges[e] for _, e in draws])).to(device)
    xy = torch.from_numpy((nodes * lattice_m).astype(np.float32)).to(device)
    target_t, z0_t = torch.from_numpy(target).to(device), torch.from_numpy(z0).to(device)
    weight_t = torch.from_numpy(weight.astype(np.float32)).to(device) if weight is not None else None
    elevation = road_map.elevation.to(device)
    opt = Adam([(elevation.parameters(), lr)])
    descent = Descent([opt], [CosineDecay(opt, steps, eta_min=FINAL_LR_FRACTION * lr)])
    with optimisation_loop("fast elevation"), step_bar(steps, "elevation", progress) as bar:
        for step in range(steps):
            bar.update()
            pick, pair = picks[step], pairs[step]
            r = elevation(torch.cat([xy[pick], xy[pair[:, 0]], xy[pair[:, 1]]]))  # one MLP pass
            r_nodes, r_a, r_b = torch.split(r, [len(pick), len(pair), len(pair)])
            if weight_t is None:
                loss_z = (r_nodes - target_t[pick]).abs().mean()
            else:
                w = weight_t[pick]
                loss_z = (w * (r_nodes - target_t[pick]).abs()).sum() / w.sum().clamp(min=1e-6)
            loss_s = ((z0_t[pair[:, 0]] + r_a - z0_t[pair[:, 1]] - r_b) ** 2).mean()
            descent.step(w_elevation * loss_z + w_smooth * loss_s)
    road_map.elevation.to(_CPU)
    return descent.losses()


def _observation_features(obs: VertexObservations, ids: np.ndarray) -> torch.Tensor:
    mean = obs.colour_mean(ids)  # (M, C, 3)
    present = (obs.colour_count[ids] > 0).astype(np.float32)[..., None]
    return torch.from_numpy(np.concatenate([mean * present, present], 2).reshape(len(ids), -1))


def _colour_l1(road_map: RoadMap, codes: torch.Tensor, target: torch.Tensor, present: torch.Tensor,
               names: list[str]) -> torch.Tensor:
    total = codes.new_zeros(())
    for c, name in enumerate(names):
        err = (road_map.decoder.decode(codes, name) - target[:, c]).abs().sum(1)
        total = total + (err * present[:, c]).sum()
    return total / (3 * present.sum()).clamp(min=1)


def fit_colours(road_map: RoadMap, obs: VertexObservations, ids: np.ndarray, encoder_steps: int, batch: int,
                lr_decoder: float, lr_encoder: float, rng: np.random.Generator,
                device: torch.device = _CPU, progress: bool = False) -> tuple[float, float]:
    """Fit the colour codes of vertices `ids` and the decoders (see module docstring); returns the L1
    colour loss of the first and the last step. The observations, the encoder and the decoders go to `device`
    once (every step's draw too, drawn before the loop), the codes and the decoders come back after."""
    names = obs.camera_names
    features = _observation_features(obs, ids).to(device)
    target = torch.from_numpy(obs.colour_mean(ids)).to(device)
    present = torch.from_numpy((obs.colour_count[ids] > 0).astype(np.float32)).to(device)
    dim = road_map.colour_params.shape[1]
    encoder = nn.Sequential(nn.Linear(features.shape[1], 64), nn.ReLU(), nn.Linear(64, dim)).to(device)
    road_map.decoder.to(device)
    decoder_params = list(road_map.decoder.parameters())
    opts = [Adam([(encoder.parameters(), lr_encoder)])]
    if decoder_params:
        opts.append(Adam([(decoder_params, lr_decoder)]))
    size = min(batch, len(ids))
    picks = torch.from_numpy(np.stack([rng.choice(len(ids), size, replace=False) for _ in range(encoder_steps)]
                                      ).reshape(encoder_steps, size)).to(device)
    descent = Descent(opts)
    with optimisation_loop("fast colour"), step_bar(encoder_steps, "colour", progress) as bar:
        for step in range(encoder_steps):
            bar.update()
            pick = picks[step]
            descent.step(_colour_l1(road_map, encoder(features[pick]), target[pick], present[pick], names))
    with torch.no_grad():
        codes = encoder(features).to(road_map.colour_params.device)
    road_map.decoder.to(_CPU)
    road_map.colour_params[torch.from_numpy(ids)] = codes
    return descent.losses()
