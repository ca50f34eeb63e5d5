"""Ray sampling as in the paper: near-surface samples around the observed depth plus a few
uniform samples over the batch's depth range; pixels without depth get uniform samples only.

"Uniform in [a, b]" is implemented as stratified jitter: [a, b] split into n equal bins and
one uniform draw per bin, which keeps samples spread out and sorted by construction.
"""

from __future__ import annotations

import torch


class RaySampler:
    """Sample depths t along rays (t is camera z-depth when ray directions have z = 1).

    Args:
        n_near: samples in [near_lo D, near_hi D] around the observed depth D.
        n_uniform: samples in [near_lo D_min, far_hi D_max], D_min/D_max the batch's
            smallest/largest valid depth.
        near_lo, near_hi, far_hi: the band's factors (0.95, 1.05, 1.05 in the paper).
        min_depth: lower end of the range for pixels without depth (D_l, 0.001 m in the paper).
        perturb: draw jittered positions (training); False puts samples at bin centres.
    """

    def __init__(
        self,
        n_near: int,
        n_uniform: int,
        *,
        near_lo: float,
        near_hi: float,
        far_hi: float,
        min_depth: float,
        perturb: bool = True,
    ) -> None:
        if n_near < 0 or n_uniform < 0 or n_near + n_uniform < 1:
            raise ValueError(f"RaySampler: need n_near, n_uniform >= 0 with a positive sum, "
                             f"got {n_near}, {n_uniform}")
        self.near_lo, self.near_hi, self.far_hi = float(near_lo), float(near_hi), float(far_hi)
        if not 0.0 < self.near_lo < self.near_hi or self.far_hi < self.near_lo:
            raise ValueError(f"RaySampler: need 0 < near_lo < near_hi and far_hi >= near_lo, got "
                             f"{self.near_lo}, {self.near_hi}, {self.far_hi}")
        self.n_near = n_near
        self.n_uniform = n_uniform
        self.min_depth = min_depth
        self.perturb = perturb

    @property
    def n_samples(self) -> int:
        """Samples per ray."""
        return self.n_near + self.n_uniform

    def __call__(
        self,
        depth_obs: torch.Tensor,
        generator: torch.Generator | None = None,
        depth_range: tuple[float, float] | None = None,
    ) -> torch.Tensor:
        """Sample depths for each ray.

        depth_obs: [R] observed depth in metres, 0 where the pixel has none.
        generator: source of the jitter; the same generator state gives the same samples.
        depth_range: (D_min, D_max) to use instead of the batch's; required when no ray of
            the batch has a depth.
        Returns t [R, n_near + n_uniform], float32, ascending along each ray, no gradient.
        """
        depth_obs = depth_obs.detach().float()
        n_rays = depth_obs.shape[0]
        has_depth = depth_obs > 0
        if depth_range is None:
            if not bool(has_depth.any()):
                raise ValueError(
                    "RaySampler: no ray in the batch has a depth; pass depth_range=(D_min, D_max)"
                )
            valid = depth_obs[has_depth]
            d_min, d_max = float(valid.min()), float(valid.max())
        else:
            d_min, d_max = float(depth_range[0]), float(depth_range[1])
            if not 0 < d_min <= d_max:
                raise ValueError(f"RaySampler: depth_range must satisfy 0 < D_min <= D_max, "
                                 f"got {depth_range}")
        lo, hi = self.near_lo, self.near_hi
        u = self._jitter(n_rays, generator, depth_obs.device)  # [R, N]

        # Rays with depth: n_near around D, n_uniform over the batch range.
        near = self._stratified(lo * depth_obs, hi * depth_obs, u[:, : self.n_near])
        uni_lo = torch.full_like(depth_obs, lo * d_min)
        uni_hi = torch.full_like(depth_obs, self.far_hi * d_max)
        uni = self._stratified(uni_lo, uni_hi, u[:, self.n_near :])
        t_depth, _ = torch.sort(torch.cat((near, uni), dim=1), dim=1)

        # Rays without depth: all samples over [min_depth, (1 + band) D_max].
        t_free = self._stratified(torch.full_like(depth_obs, self.min_depth), uni_hi, u)
        return torch.where(has_depth[:, None], t_depth, t_free)

    def _jitter(
        self, n_rays: int, generator: torch.Generator | None, device: torch.device
    ) -> torch.Tensor:
        shape = (n_rays, self.n_samples)
        if not self.perturb:
            return torch.full(shape, 0.5, device=device)
        gen_device = generator.device if generator is not None else device
        return torch.rand(shape, generator=generator, device=gen_device).to(device)

    @staticmethod
    def _stratified(lo: torch.Tensor, hi: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """n = u.shape[1] samples, one per equal bin of [lo, hi]; lo, hi: [R]."""
        n = u.shape[1]
        if n == 0:
            return u
        bins = torch.arange(n, device=u.device, dtype=u.dtype)
        frac = (bins + u) / n  # [R, n], ascending
        return lo[:, None] + (hi - lo)[:, None] * frac
