"""The shape-prior commands: `efem-viz build-codebook` and `efem-viz convert-prior` (tyro dataclasses).

Imported lazily by the CLI dispatcher; the prior modules (and torch) are imported only inside `run`. They live
here, above `efem_viz.prior.model`, `codebook` and `convert`, so that those never import the model loader back
for a command (prior/model ↔ prior/codebook was an import cycle).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import tyro
from efem_viz.prior.config import DEFAULT_PRIOR

logger = logging.getLogger(__name__)

__all__ = ["BuildCodebookArgs", "ConvertArgs", "PackMeshesArgs"]


@dataclass
class BuildCodebookArgs:
    """Build the pose codebook of a trained prior from its training-split procedural objects."""

    prior: str = DEFAULT_PRIOR
    """Prior weights: a .pt path, or a name under efem_viz/weights/ ("mug" = efem_viz/weights/mug.pt)."""
    out: Path | None = None
    """Output .npz (default: `<prior stem>_codebook.npz` next to the weights, which `load_prior` picks up)."""
    count: int = 150
    """Number of training-split objects (the first `count` seeds of the split)."""
    category: str = DEFAULT_PRIOR
    """Procedural category of the training objects, or a training family ("kitchen": its members interleaved,
    each entry classed by its category for `Codebook.category_of`)."""
    n_store: int = 2000
    """Stored noisy surface points per object (float16)."""
    noise: float = 0.01
    """Gaussian noise σ on the stored points (canonical units; training uses 0.01 for mugs)."""
    seed: int = 0
    """RNG seed of the surface sampling."""

    def run(self) -> int:
        """Build and save; returns the process exit code."""
        from efem_viz.data.procedural import FAMILIES, family_seeds, split_seeds
        from efem_viz.prior.codebook_build import build_codebook
        from efem_viz.prior.model import load_prior, resolve_prior_path

        if self.count < 1:
            raise ValueError(f"--count must be >= 1, got {self.count}")
        weights = resolve_prior_path(self.prior)
        out = self.out if self.out is not None else weights.with_name(f"{weights.stem}_codebook.npz")
        t0 = time.perf_counter()
        prior = load_prior(weights, load_codebook=False)
        seeds: list[Any] = (family_seeds(self.category, "train", self.count) if self.category in FAMILIES
                            else list(split_seeds(self.category, "train"))[: self.count])
        cb = build_codebook(
            prior, seeds, n_store=self.n_store, noise=self.noise, seed=self.seed, category=self.category
        )
        path = cb.save(out)
        logger.info(
            "codebook: %d entries, C=%d, n_store=%d, mean scale %.4f -> %s (%.1f kB, %.1f s)",
            len(cb), cb.latent_dim, cb.n_store, cb.mean_scale, path, path.stat().st_size / 1024,
            time.perf_counter() - t0,
        )
        return 0


@dataclass
class FitMemberHeadArgs:
    """Fit a family prior's member head: the classifier that names each instance's member (mug, bowl, bottle,
    can) from its latent and its completed shape's size, in place of the codebook vote."""

    prior: str = "kitchen"
    """Prior weights: a .pt path, or a name under efem_viz/weights/."""
    family: str = "kitchen"
    """The training family the prior completes (`procedural.FAMILIES`)."""
    n_train: int = 400
    """Training-split objects (the members interleaved)."""
    n_val: int = 96
    """Val-split objects: the held-out accuracy and confusion table."""
    views: int = 4
    """Partial input clouds per object."""
    seed: int = 0
    """RNG seed of the views and the fit."""
    cache_dir: Path = Path("runs/cache")
    """Per-object data cache (shared with `train-prior`)."""
    write: bool = False
    """Store the head in the prior file's metadata; EFEM then names instances by it."""

    def run(self) -> int:
        """Fit, print the held-out accuracy and confusion table; with --write update the prior. Returns 0."""
        from efem_viz.prior.member_head import METADATA_KEY, fit_member_head
        from efem_viz.prior.model import load_prior, resolve_prior_path, save_prior

        path = resolve_prior_path(self.prior)
        prior = load_prior(path, load_codebook=False)
        t0 = time.perf_counter()
        head = fit_member_head(prior, self.family, n_train=self.n_train, n_val=self.n_val, views=self.views,
                               seed=self.seed, cache_dir=self.cache_dir)
        rep = head.report
        print(f"member head of {path}: {len(head.classes)} classes, train accuracy {rep['train_accuracy']:.3f}, "
              f"val accuracy {rep['val_accuracy']:.3f} ({self.n_val} objects x {self.views} views, "
              f"{time.perf_counter() - t0:.0f} s); with each object's size {rep['val_accuracy_with_size']:.3f}")
        width = max(len(c) for c in head.classes)
        print(" " * (width + 2) + "  ".join(f"{c:>{width}}" for c in head.classes) + "   (rows: true, columns: named)")
        for c, row in zip(head.classes, rep["val_confusion"]):
            print(f"{c:>{width}}  " + "  ".join(f"{v:>{width}d}" for v in row))
        if self.write:
            save_prior(prior, path, extra={METADATA_KEY: head.to_dict()})
            print(f"wrote the member head into {path}")
        return 0


@dataclass
class PackMeshesArgs:
    """Pack a training set's meshes into one .npz that `train-prior --meshes PACK` reads without trimesh or
    open3d (a GPU machine with only torch prepares its training data from it, on the GPU)."""

    out: Path
    """Output .npz."""
    category: str = DEFAULT_PRIOR
    """Procedural category (ignored with --folder)."""
    split: Literal["train", "val", "test"] = "train"
    """Procedural seed split."""
    count: int = 400
    """Number of meshes (the first seeds of the split)."""
    handled_only: bool = False
    """Mugs with a handle only (as `train-prior --handled-only`)."""
    folder: Path | None = None
    """Pack every mesh file of this folder instead of a procedural split."""

    def run(self) -> int:
        """Build and save; returns the process exit code."""
        from efem_viz.prior.data import folder_sources, procedural_sources, save_mesh_pack

        if self.count < 1:
            raise ValueError(f"--count must be >= 1, got {self.count}")
        t0 = time.perf_counter()
        srcs = (folder_sources(self.folder) if self.folder is not None
                else procedural_sources(self.category, self.split, self.count, handled_only=self.handled_only))
        path = save_mesh_pack(srcs, self.out)
        logger.info("mesh pack: %d meshes -> %s (%.1f MB, %.1f s)", len(srcs), path, path.stat().st_size / 2**20,
                    time.perf_counter() - t0)
        return 0


@dataclass
class ConvertArgs:
    """Convert a released EFEM shape prior (weights/mugs.pt, chairs.pt or kit4cates.pt of github.com/JiahuiLei/EFEM)
    into an efem-viz prior, then build its pose codebook.

    The released priors use a +Y-up canonical frame, efem-viz +Z up. The networks are SO(3)-equivariant, so the
    weights are copied unchanged, but the released codebooks (cache/*.npz) cannot be used: the codebook is rebuilt
    here from efem-viz's +Z-up procedural meshes (`--category`), exactly as `efem-viz build-codebook` does.
    """

    src: Annotated[Path, tyro.conf.Positional]
    """The released checkpoint (a pickled dict with model_state_dict, keys network_dict.encoder./decoder.)."""
    out: Path | None = None
    """Output prior file (default: `<src stem>_efemviz.pt` next to src). Use it with `--prior PATH`."""
    name: str | None = None
    """Display name of the prior (default: mug, chair or kit4cates)."""
    release: Literal["auto", "mugs", "chairs", "kit4cates"] = "auto"
    """Which released prior (auto: from the file name, else mugs, or chairs if it has attention blocks). Sets the
    input size, down-sampling and whether the centre offset is multiplied by σ (kit4cates only)."""
    center_times_sigma: bool | None = None
    """Override: multiply the centre offset δ by σ (default: from the release)."""
    n_pcl: int | None = None
    """Override: encoder input size (default: 512 mugs/kit4cates, 1024 chairs)."""
    down_blocks: tuple[int, ...] | None = None
    """Override: down-sampled blocks (released: 2 4 5; needed for non-released depths)."""
    down_factors: tuple[int, ...] | None = None
    """Override: their down-sampling factors (released: 2 4 4, chairs 4 4 4)."""
    allow_pickle: bool = False
    """If the safe weights-only load fails, unpickle the file in full. A pickle can run code: trusted files only."""
    overwrite: bool = False
    """Replace an existing output file."""
    codebook: bool = True
    """Build the pose codebook after converting (`--no-codebook`: only convert)."""
    count: int = 150
    """Codebook: number of training-split procedural objects."""
    category: str | None = None
    """Codebook: procedural category (default: mug for mugs and kit4cates; chairs have no procedural category, so
    the codebook is skipped unless one is given)."""
    n_store: int = 2000
    """Codebook: stored noisy surface points per object."""
    noise: float = 0.01
    """Codebook: Gaussian noise σ on the stored points (canonical units)."""
    seed: int = 0
    """Codebook: RNG seed of the surface sampling."""

    def run(self) -> int:
        """Convert, then build the codebook; returns the process exit code."""
        # convert_with_release also returns the release it resolved
        from efem_viz.prior.convert import RELEASES, convert_with_release

        release = None if self.release == "auto" else self.release
        out = self.out if self.out is not None else self.src.with_name(f"{self.src.stem}_efemviz.pt")
        path, release = convert_with_release(
            self.src, out, name=self.name, release=release, center_times_sigma=self.center_times_sigma,
            n_pcl=self.n_pcl, down_blocks=self.down_blocks, down_factors=self.down_factors, k=16,
            att_head_dim=16, scale_factor=64000.0, allow_pickle=self.allow_pickle, overwrite=self.overwrite,
            check=True,
        )
        if not self.codebook:
            logger.info("--no-codebook: build it later with `efem-viz build-codebook --prior %s`", path)
            return 0
        category = self.category if self.category is not None else RELEASES[release]["category"]
        if category is None:
            logger.warning("no procedural category for the %s prior: codebook skipped. Build one from your own "
                           "+Z-up meshes with efem_viz.prior.codebook_build.build_codebook, or pass --category",
                           release)
            return 0
        return BuildCodebookArgs(prior=str(path), out=None, count=self.count, category=category,
                                 n_store=self.n_store, noise=self.noise, seed=self.seed).run()
