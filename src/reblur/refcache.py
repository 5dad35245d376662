"""What :func:`reblur.detect_changes` computes from the reference alone, kept for the next
observation (:class:`ReferenceCache`).

Comparing one reference with many observations (the frames of a video, repeated flights
over a mosaic) repeats the reference's share of the work for each of them: its
low-resolution overviews (one pass over a possibly huge, on-disk image), the reference
half of the alignment pyramid and its SIFT keypoints and descriptors.  A cache handed to
every call computes each of them once, on first use, and gives the later calls the same
arrays: the results are those of separate runs, bit for bit.

Exactness is kept by construction: every product is stored under what it was computed
from, and a run asks for it under the key a fresh run would compute it under.  An
overview derived from a finer one (:class:`~reblur.align.OverviewCache`) is keyed by the
overview it came from, so a run that would have read it directly never gets a derived one.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Hashable
from typing import Any

import numpy as np

from .align.overviews import OverviewCache

__all__ = ["ReferenceCache"]


class ReferenceCache:
    """The reference's share of :func:`reblur.detect_changes`, computed once and reused.

    Pass the same cache to every call that compares this reference with an observation
    (``detect_changes(reference, obs, reference_cache=cache)``): the first call fills it,
    the later ones reuse what does not depend on the observation.  Results are identical
    to separate runs.  ``result.decision["reference_cache"]`` says what each run reused and
    computed.

    What is kept: the reference's block-mean overviews (each ``1 / k^2`` of the image), the
    reference levels of the alignment pyramid and their no-data masks, and the SIFT
    keypoints and descriptors of those levels: a few overviews' worth of memory for each
    block factor the observations' sizes call for (observations of one size: one set,
    whatever their number).  The arrays are read-only: every later run shares them.

    Parameters
    ----------
    reference : array-like, (H, W) or (H, W, C)
        The reference, exactly the object passed to :func:`reblur.detect_changes` (numpy,
        zarr, a lazily read file, ...).

    Attributes
    ----------
    reference : array-like
        The reference.
    runs : int
        Detections that used the cache so far.

    Examples
    --------
    >>> import numpy as np
    >>> from reblur.refcache import ReferenceCache
    >>> ref = np.random.default_rng(0).random((64, 64))
    >>> cache = ReferenceCache(ref)
    >>> run = cache.begin()
    >>> a = run.overviews.block_means(4)[0]
    >>> b = cache.begin().overviews.block_means(4)[0]
    >>> a is b, cache.totals()["reused"]
    (True, {'overviews': 1})
    """

    def __init__(self, reference) -> None:
        shape = tuple(int(s) for s in getattr(reference, "shape", ()))
        if len(shape) not in (2, 3):
            raise ValueError(f"reference must be (H, W) or (H, W, C), got shape {shape}")
        self.reference = reference
        self.runs = 0
        self._store: dict[Hashable, Any] = {}
        # arrays held by the store, by id: a key may name one (it stays alive here)
        self._held: dict[int, tuple[Any, Hashable]] = {}
        self._computed: Counter[str] = Counter()
        self._reused: Counter[str] = Counter()

    def __repr__(self) -> str:
        return (f"ReferenceCache(shape={tuple(self.reference.shape)}, runs={self.runs}, "
                f"entries={len(self._store)})")

    def begin(self) -> ReferenceRun:
        """The view of one detection: its overviews and its record of what it reused."""
        self.runs += 1
        return ReferenceRun(self)

    def token(self, array) -> Hashable | None:
        """A key standing for ``array`` when the cache holds it (an overview or pyramid
        level it handed out), else None: products of it may then be cached under it."""
        got = self._held.get(id(array))
        return got[1] if got is not None and got[0] is array else None

    def get(self, kind: str, key: Hashable, compute: Callable[[], Any],
            counts: Counter[str] | None = None) -> tuple[Any, bool]:
        """``(value, reused)``: the value stored under ``(kind, key)``, computed by
        ``compute()`` the first time.  Arrays in the value become tokens
        (:meth:`token`)."""
        full = (kind, key)
        reused = full in self._store
        if not reused:
            value = compute()
            self._store[full] = value
            for i, a in enumerate(value if isinstance(value, tuple) else (value,)):
                if isinstance(a, np.ndarray):  # (an array held already keeps its token)
                    a.flags.writeable = False  # shared by every later run: never changed
                    self._held.setdefault(id(a), (a, (full, i)))
        (self._reused if reused else self._computed)[kind] += 1
        if counts is not None:
            counts[("reused " if reused else "computed ") + kind] += 1
        return self._store[full], reused

    def totals(self) -> dict[str, Any]:
        """What the cache computed and how often its entries were reused, by kind."""
        return dict(runs=self.runs, computed=dict(self._computed), reused=dict(self._reused),
                    bytes=int(self.nbytes))

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays held."""
        bases = {}
        for a, _ in self._held.values():
            b = a if a.base is None else a.base  # a view counts with what it views
            bases[id(b)] = b.nbytes if isinstance(b, np.ndarray) else a.nbytes
        return int(sum(bases.values()))


class ReferenceRun:
    """One detection's view of a :class:`ReferenceCache`.

    Attributes
    ----------
    overviews : OverviewCache
        Stands in for the reference in the detection (``shape``, ``dtype``, reads): its
        block-mean overviews come from the cache.
    """

    def __init__(self, cache: ReferenceCache) -> None:
        self.cache = cache
        self.counts: Counter[str] = Counter()
        self.overviews = _SharedOverviews(cache, self)

    def memo(self, kind: str, key: Hashable, compute: Callable[[], Any]) -> Any:
        """The value of ``compute()`` from the cache, stored under ``(kind, key)``."""
        return self.cache.get(kind, key, compute, self.counts)[0]

    def token(self, array) -> Hashable | None:
        """:meth:`ReferenceCache.token`."""
        return self.cache.token(array)

    def to_dict(self) -> dict[str, Any]:
        """What this run reused and computed, for the report."""
        reused = {k.split(" ", 1)[1]: v for k, v in self.counts.items()
                  if k.startswith("reused ")}
        computed = {k.split(" ", 1)[1]: v for k, v in self.counts.items()
                    if k.startswith("computed ")}
        return dict(run=self.cache.runs, reused=reused, computed=computed,
                    cache_bytes=int(self.cache.nbytes))


class _SharedOverviews(OverviewCache):
    """An :class:`~reblur.align.OverviewCache` of the reference whose overviews come from a
    :class:`ReferenceCache`.

    It sees (for :meth:`factor` and derivations) only the overviews this run asked for,
    as a fresh cache would, and takes each from the shared store under the key of how a
    fresh cache makes it: read directly, or block-averaged from the overview it already
    holds.  So a run gets the arrays a separate run computes."""

    def __init__(self, cache: ReferenceCache, run: ReferenceRun) -> None:
        super().__init__(cache.reference)
        self._run = run
        self._keys: dict[int, Hashable] = {}
        #: the run's memo of the reference's products (see reblur.align.coarse._prepare)
        self.reference_run = run

    def block_means(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        k = int(k)
        if k not in self._memo:
            divisors = [k0 for k0 in self._memo if k % k0 == 0]
            key = (k, self._keys[max(divisors)]) if divisors else (k, None)
            # computed the way the base class does it, from what this run holds, and
            # stored flat with where it came from (the cache hands out tokens of the
            # arrays at the top level of a value)
            *value, source = self._run.memo(
                "overviews", key,
                lambda: (*OverviewCache.block_means(self, k), self._sources[k]))
            self._memo[k] = tuple(value)
            self._sources[k] = source
            self._keys[k] = key
        return self._memo[k]
