"""The neural point map: a structure of arrays of points anchored to keyframes.

Each point stores its position in its anchor keyframe's camera frame; world positions are the
anchor's pose applied to it. Correcting keyframe poses (pose graph, alignment to another
agent's frame) therefore moves the points with no other bookkeeping.

Features live in one `nn.Parameter` [N, F] owned by the map. Adding, removing or merging points
replaces that Parameter with a new one, so an optimiser holding the old one goes stale: the
mapper builds its Adam over `map.features` at the start of every mapping call (the paper resets
the feature learning-rate decay there anyway) and never across calls that change the map. To
optimise a subset only, the mapper can pass a tensor of its own as `features=` to the renderer
(e.g. `map.features.detach().index_copy(0, rows, active)` with `active` a leaf [M, F]) and
write `active` back with `map.set_features(rows, active)` afterwards.

Keyframes are keyed by (agent id, keyframe id): keyframe ids only need to be unique per agent,
so maps of different agents merge without renumbering. Points are keyed by (agent id,
point id), point ids increasing per agent.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import nn

from cpslam.common.field.grid import grid_winners
from cpslam.common.field.search import NeighbourIndex

logger = logging.getLogger(__name__)

FORMAT_VERSION = 1
_POINT_FIELDS = ("anchor_kf", "xyz_local", "features", "agent_id", "point_id", "color")


class NeuralPointMap:
    """Neural points anchored to keyframes (structure of arrays on one device).

    Args:
        feature_dim: width F of the point features.
        cell_size: grid-filter cell rho in metres.
        default_agent: agent id used where a method's agent_id is left out.
        device: device of all tensors.

    Per-point tensors (N points): anchor_kf int64 [N], xyz_local float32 [N, 3] (anchor camera
    frame), features nn.Parameter float32 [N, F], agent_id int32 [N], point_id int64 [N],
    color uint8 [N, 3]. Keyframes: kf_keys int64 [K, 2] (agent, keyframe id), kf_poses float64
    [K, 4, 4] (T_world_kf). `version` grows with every change of points or poses.
    """

    def __init__(
        self,
        feature_dim: int,
        cell_size: float,
        default_agent: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        if feature_dim < 1 or cell_size <= 0:
            raise ValueError(f"NeuralPointMap: need feature_dim >= 1 and cell_size > 0, got "
                             f"{feature_dim}, {cell_size}")
        self.feature_dim = feature_dim
        self.cell_size = float(cell_size)
        self.default_agent = int(default_agent)
        self.device = torch.device(device)
        dev = self.device
        self.anchor_kf = torch.zeros(0, dtype=torch.int64, device=dev)
        self.xyz_local = torch.zeros(0, 3, dtype=torch.float32, device=dev)
        self.features = nn.Parameter(torch.zeros(0, feature_dim, device=dev))
        self.agent_id = torch.zeros(0, dtype=torch.int32, device=dev)
        self.point_id = torch.zeros(0, dtype=torch.int64, device=dev)
        self.color = torch.zeros(0, 3, dtype=torch.uint8, device=dev)
        self.kf_keys = torch.zeros(0, 2, dtype=torch.int64, device=dev)
        self.kf_poses = torch.zeros(0, 4, 4, dtype=torch.float64, device=dev)
        self.next_point_id: dict[int, int] = {}
        self.version = 0
        self._kf_row: dict[tuple[int, int], int] = {}
        self._xyz_cache: tuple[int, torch.Tensor] | None = None
        self._index_cache: NeighbourIndex | None = None

    def __len__(self) -> int:
        return int(self.xyz_local.shape[0])

    # ----------------------------------------------------------------------------- keyframes

    def set_keyframe_poses(
        self,
        kf_ids: int | Sequence[int] | torch.Tensor,
        T_world_kf: torch.Tensor | np.ndarray,
        agent_id: int | None = None,
    ) -> None:
        """Add keyframes or move existing ones (and with them all their points).

        kf_ids: one id or K ids; T_world_kf: [4, 4] or [K, 4, 4].
        """
        agent = self.default_agent if agent_id is None else int(agent_id)
        ids = torch.as_tensor(kf_ids, dtype=torch.int64).reshape(-1).tolist()
        poses = torch.as_tensor(T_world_kf, dtype=torch.float64).reshape(-1, 4, 4)
        if poses.shape[0] != len(ids):
            raise ValueError(f"set_keyframe_poses: {len(ids)} ids but {poses.shape[0]} poses")
        _check_rigid(poses, "set_keyframe_poses: T_world_kf")
        poses = poses.to(self.device)
        new_keys, new_poses = [], []
        for i, kf in enumerate(ids):
            row = self._kf_row.get((agent, kf))
            if row is None:
                self._kf_row[(agent, kf)] = len(self._kf_row)
                new_keys.append((agent, kf))
                new_poses.append(poses[i])
            else:
                self.kf_poses[row] = poses[i]
        if new_keys:
            keys = torch.tensor(new_keys, dtype=torch.int64, device=self.device)
            self.kf_keys = torch.cat((self.kf_keys, keys))
            self.kf_poses = torch.cat((self.kf_poses, torch.stack(new_poses)))
        self._touch()

    def keyframe_pose(self, kf_id: int, agent_id: int | None = None) -> torch.Tensor:
        """T_world_kf [4, 4] float64 of one keyframe."""
        return self.kf_poses[self._row_of(int(kf_id), agent_id)].clone()

    def has_keyframe(self, kf_id: int, agent_id: int | None = None) -> bool:
        agent = self.default_agent if agent_id is None else int(agent_id)
        return (agent, int(kf_id)) in self._kf_row

    # ------------------------------------------------------------------------------- points

    def xyz_world(self) -> torch.Tensor:
        """World positions [N, 3] float32 (detached; cached until the map changes)."""
        if self._xyz_cache is not None and self._xyz_cache[0] == self.version:
            return self._xyz_cache[1]
        rows = self._anchor_rows()
        T = self.kf_poses[rows]  # [N, 4, 4]
        local = self.xyz_local.double()
        xyz = (T[:, :3, :3] @ local[:, :, None])[:, :, 0] + T[:, :3, 3]
        xyz = xyz.float()
        self._xyz_cache = (self.version, xyz)
        return xyz

    def neighbour_index(self, backend: str = "auto", workers: int = 1) -> NeighbourIndex:
        """Search structure over `xyz_world()`, rebuilt only when points or poses changed."""
        cached = self._index_cache
        if cached is None or cached.version != self.version or (
            backend != "auto" and cached.backend != backend
        ):
            cached = NeighbourIndex(self.xyz_world(), backend, workers, self.version)
            self._index_cache = cached
        return cached

    def add_points(
        self,
        xyz_world: torch.Tensor,
        anchor_kf: int | torch.Tensor,
        features: torch.Tensor,
        colors: torch.Tensor | np.ndarray,
        agent_id: int | None = None,
    ) -> torch.Tensor:
        """Add points given in world coordinates, anchored to `anchor_kf` of `agent_id`.

        Grid filter: a new point whose cell already holds a point is dropped (existing points
        stay); among new points sharing an empty cell the one nearest the cell centre is kept.
        xyz_world [M, 3], features [M, F], colors uint8 [M, 3]; anchor_kf an id or [M] ids, all
        already registered with `set_keyframe_poses`. Returns the point ids added, int64 [M'].
        """
        agent = self.default_agent if agent_id is None else int(agent_id)
        xyz_world = torch.as_tensor(xyz_world, device=self.device).detach()
        m = xyz_world.shape[0]
        if xyz_world.shape != (m, 3):
            raise ValueError(f"add_points: xyz_world must be [M, 3], got {tuple(xyz_world.shape)}")
        features = torch.as_tensor(features, device=self.device).detach().float()
        if features.shape != (m, self.feature_dim):
            raise ValueError(f"add_points: features must be [{m}, {self.feature_dim}], "
                             f"got {tuple(features.shape)}")
        colors = torch.as_tensor(colors, device=self.device)
        if colors.shape != (m, 3) or colors.dtype != torch.uint8:
            raise ValueError(f"add_points: colors must be uint8 [{m}, 3], got "
                             f"{colors.dtype} {tuple(colors.shape)}")
        anchors = torch.as_tensor(anchor_kf, dtype=torch.int64, device=self.device).reshape(-1)
        anchors = anchors.expand(m) if anchors.numel() == 1 else anchors
        if anchors.shape != (m,):
            raise ValueError(f"add_points: anchor_kf must be one id or [{m}] ids")
        if m == 0:
            return torch.zeros(0, dtype=torch.int64, device=self.device)

        existing = self.xyz_world().double().cpu().numpy()
        new = xyz_world.double().cpu().numpy()
        keep = grid_winners(
            np.concatenate((existing, new)), self.cell_size, n_fixed=len(existing)
        )[len(existing):]
        keep_t = torch.from_numpy(keep).to(self.device)
        anchors = anchors[keep_t]
        anchor_ids, anchor_inv = torch.unique(anchors, return_inverse=True)
        rows = torch.tensor(
            [self._row_of(kf, agent) for kf in anchor_ids.tolist()],
            dtype=torch.int64, device=self.device,
        )[anchor_inv]
        T = self.kf_poses[rows]
        delta = xyz_world[keep_t].double() - T[:, :3, 3]
        local = (T[:, :3, :3].transpose(1, 2) @ delta[:, :, None])[:, :, 0]
        first = self.next_point_id.get(agent, 0)
        ids = torch.arange(first, first + len(rows), dtype=torch.int64, device=self.device)
        self.next_point_id[agent] = first + len(rows)
        self._append(
            anchor_kf=anchors,
            xyz_local=local.float(),
            features=features[keep_t],
            agent_id=torch.full((len(rows),), agent, dtype=torch.int32, device=self.device),
            point_id=ids,
            color=colors[keep_t],
        )
        logger.debug("add_points: kept %d of %d (map now %d)", len(rows), m, len(self))
        return ids

    def grid_filter(self) -> int:
        """Keep one point per cell, the one nearest the cell centre. Returns how many went."""
        keep = grid_winners(self.xyz_world().double().cpu().numpy(), self.cell_size)
        removed = int((~keep).sum())
        if removed:
            self._keep(torch.from_numpy(keep).to(self.device))
        return removed

    def rows_of(self, point_ids: torch.Tensor | Sequence[int], agent_id: int | None = None
                ) -> torch.Tensor:
        """Rows (positions in the arrays) of the given point ids of one agent, int64 [M];
        ids not in the map are skipped."""
        agent = self.default_agent if agent_id is None else int(agent_id)
        ids = torch.as_tensor(point_ids, dtype=torch.int64, device=self.device).reshape(-1)
        mask = (self.agent_id == agent) & torch.isin(self.point_id, ids)
        return mask.nonzero(as_tuple=True)[0]

    def remove(self, point_ids: torch.Tensor | Sequence[int], agent_id: int | None = None) -> int:
        """Remove points by id (of one agent). Returns how many were removed."""
        rows = self.rows_of(point_ids, agent_id)
        if len(rows):
            keep = torch.ones(len(self), dtype=torch.bool, device=self.device)
            keep[rows] = False
            self._keep(keep)
        return int(len(rows))

    def subset(self, mask: torch.Tensor) -> NeuralPointMap:
        """A new map with the points where mask [N] is true (all keyframes kept)."""
        mask = torch.as_tensor(mask, device=self.device)
        out = self._empty_like()
        out.kf_keys, out.kf_poses = self.kf_keys.clone(), self.kf_poses.clone()
        out._kf_row = dict(self._kf_row)
        out.next_point_id = dict(self.next_point_id)
        for name in _POINT_FIELDS:
            value = getattr(self, name).detach()[mask].clone()
            setattr(out, name, nn.Parameter(value) if name == "features" else value)
        out._touch()
        return out

    def set_features(self, rows: torch.Tensor, values: torch.Tensor) -> None:
        """Write features [M, F] into the given rows (after optimising a subset)."""
        with torch.no_grad():
            self.features[rows.to(self.device)] = values.detach().to(self.device)

    def merge(
        self,
        other: NeuralPointMap,
        T_this_other: torch.Tensor | np.ndarray,
        grid_filter: bool = True,
    ) -> None:
        """Bring `other` (keyframes and points) into this map's frame and append it.

        T_this_other [4, 4] maps other's world frame into this one. Keyframe keys and point
        keys must not collide. With `grid_filter`, the fused map keeps one point per cell.
        """
        if other.feature_dim != self.feature_dim:
            raise ValueError(f"merge: feature_dim {other.feature_dim} != {self.feature_dim}")
        T = torch.as_tensor(T_this_other, dtype=torch.float64).reshape(4, 4)
        _check_rigid(T[None], "merge: T_this_other")
        clash = set(self._kf_row) & set(other._kf_row)
        if clash:
            raise ValueError(f"merge: keyframes (agent, id) present in both maps: "
                             f"{sorted(clash)[:5]}")
        keys = torch.cat((_point_keys(self), _point_keys(other).to(self.device)))
        if len(torch.unique(keys)) != len(keys):
            raise ValueError("merge: some (agent, point id) pairs are present in both maps")
        poses = T.to(self.device) @ other.kf_poses.to(self.device)
        for i, (agent, kf) in enumerate(other.kf_keys.tolist()):
            self._kf_row[(agent, kf)] = len(self.kf_keys) + i
        self.kf_keys = torch.cat((self.kf_keys, other.kf_keys.to(self.device)))
        self.kf_poses = torch.cat((self.kf_poses, poses))
        for agent, nxt in other.next_point_id.items():
            self.next_point_id[agent] = max(nxt, self.next_point_id.get(agent, 0))
        self._append(**{n: getattr(other, n).detach().to(self.device) for n in _POINT_FIELDS})
        if grid_filter:
            removed = self.grid_filter()
            logger.debug("merge: grid filter removed %d points", removed)

    # ---------------------------------------------------------------------------- save/load

    def state_dict(self) -> dict:
        """Plain tensors and numbers on the CPU (loadable with torch.load(weights_only=True))."""
        agents = sorted(self.next_point_id)
        return {
            "format_version": FORMAT_VERSION,
            "feature_dim": self.feature_dim,
            "cell_size": self.cell_size,
            "default_agent": self.default_agent,
            **{n: getattr(self, n).detach().cpu().clone() for n in _POINT_FIELDS},
            "kf_keys": self.kf_keys.cpu().clone(),
            "kf_poses": self.kf_poses.cpu().clone(),
            "next_point_id": torch.tensor(
                [[a, self.next_point_id[a]] for a in agents], dtype=torch.int64
            ).reshape(-1, 2),
        }

    def load_state_dict(self, state: dict, source: str = "state_dict") -> None:
        """Replace this map's content by `state` (as written by `state_dict`)."""
        missing = [k for k in ("format_version", "kf_keys", "kf_poses", "next_point_id",
                               *_POINT_FIELDS) if k not in state]
        if missing:
            raise ValueError(f"{source}: not a neural point map, missing fields {missing}")
        if int(state["format_version"]) != FORMAT_VERSION:
            raise ValueError(f"{source}: format_version {state['format_version']}, "
                             f"expected {FORMAT_VERSION}")
        self.feature_dim = int(state["feature_dim"])
        self.cell_size = float(state["cell_size"])
        self.default_agent = int(state["default_agent"])
        n = state["xyz_local"].shape[0]
        expected = {
            "anchor_kf": ((n,), torch.int64), "xyz_local": ((n, 3), torch.float32),
            "features": ((n, self.feature_dim), torch.float32), "agent_id": ((n,), torch.int32),
            "point_id": ((n,), torch.int64), "color": ((n, 3), torch.uint8),
        }
        for name, (shape, dtype) in expected.items():
            value = state[name]
            if tuple(value.shape) != shape or value.dtype != dtype:
                raise ValueError(f"{source}: field {name} is {value.dtype} {tuple(value.shape)}, "
                                 f"expected {dtype} {shape}")
            value = value.to(self.device).clone()
            setattr(self, name, nn.Parameter(value) if name == "features" else value)
        kf_keys, kf_poses = state["kf_keys"], state["kf_poses"]
        if kf_keys.ndim != 2 or kf_keys.shape[1] != 2 or kf_poses.shape != (len(kf_keys), 4, 4):
            raise ValueError(f"{source}: kf_keys {tuple(kf_keys.shape)} / kf_poses "
                             f"{tuple(kf_poses.shape)} are not [K, 2] / [K, 4, 4]")
        self.kf_keys = kf_keys.to(self.device, torch.int64).clone()
        self.kf_poses = kf_poses.to(self.device, torch.float64).clone()
        self._kf_row = {(a, k): i for i, (a, k) in enumerate(self.kf_keys.tolist())}
        self.next_point_id = {int(a): int(v) for a, v in state["next_point_id"].tolist()}
        try:
            self._anchor_rows()
        except KeyError as err:
            msg = f"{source}: a point's anchor keyframe is not in kf_keys ({err})"
            raise ValueError(msg) from None
        self._touch()

    def save(self, path: str | Path) -> None:
        """Write the whole map to one file (torch.save of plain tensors), atomically."""
        from cpslam.common.durable import torch_save_atomic

        torch_save_atomic(self.state_dict(), path)

    @classmethod
    def load(cls, path: str | Path, device: str | torch.device = "cpu") -> NeuralPointMap:
        """Read a map written by `save`."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"neural point map file not found: {path}")
        state = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(state, dict):
            raise ValueError(f"{path}: not a neural point map file")
        # The state holds the feature width and cell; these placeholders are replaced.
        out = cls(feature_dim=1, cell_size=1.0, device=device)
        out.load_state_dict(state, source=str(path))
        return out

    def to(self, device: str | torch.device) -> NeuralPointMap:
        """Move every tensor to `device` (features become a new Parameter); returns self."""
        self.device = torch.device(device)
        for name in (*_POINT_FIELDS, "kf_keys", "kf_poses"):
            value = getattr(self, name).detach().to(self.device)
            setattr(self, name, nn.Parameter(value) if name == "features" else value)
        self._touch()
        return self

    # ------------------------------------------------------------------------------ private

    def _touch(self) -> None:
        self.version += 1

    def _row_of(self, kf_id: int, agent_id: int | None) -> int:
        agent = self.default_agent if agent_id is None else int(agent_id)
        row = self._kf_row.get((agent, kf_id))
        if row is None:
            raise KeyError(f"keyframe {kf_id} of agent {agent} is not in the map; "
                           "register it with set_keyframe_poses first")
        return row

    def _anchor_rows(self) -> torch.Tensor:
        """Row of each point's anchor keyframe in kf_poses, int64 [N]."""
        if len(self) == 0:
            return torch.zeros(0, dtype=torch.int64, device=self.device)
        # Match (agent, kf) pairs through one packed int64 key per pair.
        table = self.kf_keys[:, 0] * (1 << 40) + self.kf_keys[:, 1]
        order = torch.argsort(table)
        wanted = self.agent_id.long() * (1 << 40) + self.anchor_kf
        pos = torch.searchsorted(table[order], wanted).clamp(max=max(len(table) - 1, 0))
        if len(table) == 0 or not bool((table[order][pos] == wanted).all()):
            raise KeyError("unknown anchor keyframe")
        return order[pos]

    def _append(self, **fields: torch.Tensor) -> None:
        for name in _POINT_FIELDS:
            joined = torch.cat((getattr(self, name).detach(), fields[name]))
            setattr(self, name, nn.Parameter(joined) if name == "features" else joined)
        self._touch()

    def _keep(self, mask: torch.Tensor) -> None:
        for name in _POINT_FIELDS:
            kept = getattr(self, name).detach()[mask]
            setattr(self, name, nn.Parameter(kept) if name == "features" else kept)
        self._touch()

    def _empty_like(self) -> NeuralPointMap:
        return NeuralPointMap(self.feature_dim, self.cell_size, self.default_agent, self.device)


def _point_keys(point_map: NeuralPointMap) -> torch.Tensor:
    """One int64 per point from (agent id, point id)."""
    return point_map.agent_id.long() * (1 << 40) + point_map.point_id


def _check_rigid(T: torch.Tensor, what: str, tol: float = 1e-4) -> None:
    """Raise if any of T [K, 4, 4] is not a rigid transform."""
    R = T[:, :3, :3]
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    ortho = (R.transpose(1, 2) @ R - eye).abs().amax(dim=(1, 2))
    last_row = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device)
    bottom = (T[:, 3] - last_row).abs().amax(dim=1)
    finite = torch.isfinite(T).flatten(1).all(dim=1)
    bad = ~finite | (ortho > tol) | (torch.linalg.det(R) < 0) | (bottom > tol)
    if bool(bad.any()):
        raise ValueError(f"{what}: not a rigid transform (index {int(bad.nonzero()[0])})")

