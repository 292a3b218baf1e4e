"""What a server grants one session's config, beyond the engine's own ranges."""

from __future__ import annotations

from dataclasses import dataclass

from ogmapping.config.fields import ranged
from ogmapping.config.resolution import highest
from ogmapping.config.sections import MAX_OCTREE_LEVEL, MapperConfig, ModelConfig

MIB = 1 << 20


@dataclass
class ConfigBounds:
    """The most one session's config may ask for: what a server grants its clients, on top of
    ``validate``'s ranges. Each bound names the config keys it limits; a server operator tightens
    (or widens) them in the server settings (``config_bounds``), within each bound's own range."""

    max_iterations: int = ranged(500, 1)  # keyframes.first_iterations, keyframes.iterations, keyframes.frame_iterations
    max_window_keyframes: int = ranged(16, 1)  # keyframes.local_count + keyframes.global_count
    max_n_offsets: int = ranged(32, 1)  # model.n_offsets
    max_feature_dim: int = ranged(256, 1)  # model.feature_dim, model.hidden_dim
    max_hash_levels: int = ranged(32, 1)  # model.hash_levels
    max_hash_features_per_level: int = ranged(16, 1)  # model.hash_features_per_level
    # model.hash_levels x 2^model.hash_log2_size x hash_features_per_level x 4 bytes
    max_hash_table_mib: int = ranged(256, 1)
    max_octree_level: int = ranged(MAX_OCTREE_LEVEL, 1)  # octree.max_level
    # octree.voxel_size, metres: smaller coarse cells mean more anchors
    min_voxel_size: float = ranged(0.01, 0, open_low=True)
    max_new_anchors: int = ranged(100000, 1)  # refine.max_new_anchors

    def caps(self, config: MapperConfig) -> dict[str, float]:
        """What a resolution rule may make of each follower (``resolution.FOLLOWERS``) under these bounds: a
        frame's step counts times the step multiple stay within ``max_iterations``. ``check`` holds the
        others at the most their rules can make."""
        keyframes = config.keyframes
        most = max(keyframes.first_iterations, keyframes.iterations, keyframes.frame_iterations, 1)
        return {"steps": max(1, self.max_iterations // most)}

    def check(self, config: MapperConfig) -> None:
        """Raise ValueError naming the first config key beyond these bounds."""
        model, keyframes = config.model, config.keyframes
        limits: list[tuple[str, float, float, str]] = [
            *((f"keyframes.{name}", getattr(keyframes, name), self.max_iterations, "max_iterations")
              for name in ("first_iterations", "iterations", "frame_iterations")),
            ("keyframes.local_count + keyframes.global_count", keyframes.local_count + keyframes.global_count,
             self.max_window_keyframes, "max_window_keyframes"),
            # Counted at the most that the resolution rules may make of them once the first frame arrives.
            ("model.n_offsets (at most, by resolution.n_offsets)", highest(config, "n_offsets"), self.max_n_offsets,
             "max_n_offsets"),
            ("model.feature_dim", model.feature_dim, self.max_feature_dim, "max_feature_dim"),
            ("model.hidden_dim", model.hidden_dim, self.max_feature_dim, "max_feature_dim"),
            ("octree.max_level (at most, by resolution.max_level)", highest(config, "max_level"),
             self.max_octree_level, "max_octree_level"),
            ("refine.max_new_anchors", config.refine.max_new_anchors, self.max_new_anchors, "max_new_anchors"),
        ]
        if model.encoding == "hash":  # the anchor encoding has no hash table
            limits += [
                ("model.hash_levels", model.hash_levels, self.max_hash_levels, "max_hash_levels"),
                ("model.hash_features_per_level", model.hash_features_per_level, self.max_hash_features_per_level,
                 "max_hash_features_per_level"),
            ]
        for key, value, limit, name in limits:
            if value > limit:
                raise ValueError(f"config {key} = {value} is above this server's limit of {limit} "
                                 f"(config_bounds.{name})")
        if config.octree.voxel_size < self.min_voxel_size:
            raise ValueError(f"config octree.voxel_size = {config.octree.voxel_size} is below this server's "
                             f"limit of {self.min_voxel_size} (config_bounds.min_voxel_size)")
        table_mib = hash_table_bytes(model) / MIB
        if model.encoding == "hash" and table_mib > self.max_hash_table_mib:
            raise ValueError(f"config model.hash_log2_size = {model.hash_log2_size} makes a {table_mib:g} MiB hash "
                             f"table (hash_levels x 2^hash_log2_size x hash_features_per_level x 4 bytes), above "
                             f"this server's limit of {self.max_hash_table_mib} MiB (config_bounds.max_hash_table_mib)")


def hash_table_bytes(model: ModelConfig) -> int:
    """The dense encoding's table (float32); its gradient (rows, or a buffer of the table's size on the CPU) and
    Adam moments take about three times more."""
    return model.hash_levels * 2**model.hash_log2_size * model.hash_features_per_level * 4
