"""A store's global vectors (``Workspace.global_vectors``): each drive's encoder (codebook and PCA) and one
vector per image, which the camera-rate path and a sharded store's global index search."""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path

import numpy as np

from visloc.db import VectorTable
from visloc.errors import InputError
from visloc.features.vlad import GlobalEncoder, GlobalIndex
from visloc.params import FAST, FastParams
from visloc.store.database import GeoDatabase


class GlobalVectors:
    """The global vectors of the store at ``path``. ``open_store()``: a short-lived connection to it;
    ``cover(source, camera)``: a sharded store's catalogue holds that drive from then on; ``drives()``: the
    drives it holds (``Workspace`` gives its own)."""

    def __init__(self, path: Path, open_store: Callable[[], AbstractContextManager],
                 cover: Callable[[str, str], None], drives: Callable[[], list]):
        self.path = path
        self._store = open_store
        self._cover = cover
        self._drives = drives

    def stored_vector_ids(self, name: str) -> set[int]:
        """The images that have a global vector called ``name``."""
        with self._store() as store:
            return set(VectorTable(store).stored_vector_ids(name))

    def load_database_index(self, db: GeoDatabase, params: FastParams = FAST) -> GlobalIndex | None:
        """The stored global vectors of ``db``'s images in its order, or None when any image lacks one."""
        name = global_vectors_name(db.source, db.camera, params)
        self._cover(db.source, db.camera)
        if not self.has_global_index(name):
            return None
        ids, index = self.load_global_index(name)
        row_of = {int(i): r for r, i in enumerate(ids)}
        rows = [row_of.get(im.image_id) for im in db.images]
        if any(r is None for r in rows):
            return None
        return GlobalIndex(index.encoder, index.vectors_f32[rows])

    def save_global_encoder(self, name: str, encoder: GlobalEncoder) -> None:
        """Keep the encoder of the global vectors called ``name`` (its codebook and PCA)."""
        with self._store() as store:
            VectorTable(store).put_array(f"{name}_codebook", encoder.codebook_f32)
            if encoder.pca_basis_f32 is not None:
                VectorTable(store).put_array(f"{name}_pca_mean", encoder.pca_mean_f32)
                VectorTable(store).put_array(f"{name}_pca_basis", encoder.pca_basis_f32)

    def add_global_vectors(self, name: str, image_ids, vectors_f32: np.ndarray) -> None:
        """Keep one global vector per image under ``name`` (replacing what was there)."""
        with self._store() as store:
            VectorTable(store).add_global_vectors(name, list(image_ids), vectors_f32)

    def global_vectors_by_image(self, params: FastParams = FAST) -> tuple[str, dict[int, np.ndarray]]:
        """(the names joined, image id -> global vector) of every dataset's global vectors made with ``params``."""
        names, vectors = [], {}
        for d in self._drives():
            name = global_vectors_name(d.source, d.camera, params)
            if self.has_global_index(name):
                image_ids, index = self.load_global_index(name)
                vectors.update(zip(image_ids.tolist(), index.vectors_f32))
                names.append(name)
        return ";".join(names), vectors

    def has_global_index(self, name: str) -> bool:
        with self._store() as store:
            return VectorTable(store).get_array(f"{name}_codebook") is not None

    def load_global_encoder(self, name: str) -> GlobalEncoder:
        with self._store() as store:
            table = VectorTable(store)
            return GlobalEncoder(table.get_array(f"{name}_codebook"), table.get_array(f"{name}_pca_mean"),
                                 table.get_array(f"{name}_pca_basis"))

    def load_global_index(self, name: str) -> tuple[np.ndarray, GlobalIndex]:
        """(image ids (N,), the index) of the global vectors called ``name``, in image id order."""
        with self._store() as store:
            codebook = VectorTable(store).get_array(f"{name}_codebook")
            if codebook is None:
                raise InputError(f"{self.path}: no global vectors named {name!r}")
            encoder = GlobalEncoder(codebook, VectorTable(store).get_array(f"{name}_pca_mean"),
                                    VectorTable(store).get_array(f"{name}_pca_basis"))
            ids, vectors = VectorTable(store).global_vectors(name)
        return ids, GlobalIndex(encoder, vectors)


def global_vectors_name(source: str, camera: str, params: FastParams) -> str:
    """The name a store keeps (source, camera)'s global vectors under, for the encoder ``params`` describe."""
    return (f"vlad:{source}/{camera}:words={params.n_words},pca={params.pca_dim},"
            f"train={params.train_descriptors},seed={params.seed}")
