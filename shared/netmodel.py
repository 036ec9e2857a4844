"""Network latency models for end-to-end latency (VLA-Perf): bytes / bandwidth + base latency, each way."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Network:
    name: str
    up_mbit_s: float
    down_mbit_s: float
    base_one_way_ms: float

    def latency_s(self, up_bytes: int, down_bytes: int) -> float:
        """Round-trip network time of one request of ``up_bytes`` and its reply of ``down_bytes``."""
        if self.up_mbit_s == 0:
            return 0.0
        up = up_bytes * 8 / (self.up_mbit_s * 1e6)
        down = down_bytes * 8 / (self.down_mbit_s * 1e6)
        return up + down + 2 * self.base_one_way_ms / 1e3


NETWORKS: dict[str, Network] = {
    "wifi7": Network("wifi7", 2100, 3000, 2.5),
    "fast_cloud": Network("fast_cloud", 10_000, 10_000, 10.0),
    "slow_cloud": Network("slow_cloud", 1_000, 1_000, 100.0),
    "5g": Network("5g", 80, 500, 10.0),
    "none": Network("none", 0, 0, 0.0),
}
