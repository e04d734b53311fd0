"""Training tuples and evaluation sets of the PointNetVLAD benchmark, in our format and theirs.

The rules follow the published scripts (``generate_training_tuples_baseline.py``,
``generate_test_sets.py``); docs/SPLITS.md states each one with its boundary:

- Test regions (:mod:`.regions`): a submap is inside when, for some centre (cn, ce),
  ``cn - w < northing < cn + w`` and ``ce - w < easting < ce + w`` (strict; w = 150 m).
- Training tuples (:mod:`.tuples`; training layout, submaps outside the test regions, all runs
  of a dataset pooled, runs sorted, CSV row order): positives of i are the other submaps j with
  ``d(i, j) <= pos_radius`` (10 m, inclusive); negatives those with ``d(i, j) > neg_radius``
  (50 m). Every submap is kept as an entry, as in the published pickle; the rule "an anchor needs
  at least 2 positives" is the trainer's (``TrainingTuples.anchors(min_positives=2)``).
- Evaluation sets (:mod:`.evaluation`; test layout, per run): the database is every submap of
  the run; the queries are its submaps inside the test regions; ``truth[j][i][q]`` lists run
  i's database submaps with ``d <= truth_radius`` (25 m, inclusive) of query q of run j, for
  every i != j.

Distances (:mod:`.geometry`) are Euclidean in (northing, easting), computed as
``dn² + de² <= r²`` in float64 from coordinate differences, so points exactly r metres away
along one axis are inside. :func:`build_splits` (:mod:`.build`) makes all of it for a tree;
:mod:`.codec` is our JSON format, :mod:`.pickles` the published pickles.

This package's public face: ``from pnvlad_service.data import splits as sp; sp.build_splits(...)``.
"""

from __future__ import annotations

from pnvlad_service.data.splits.build import (
    OXFORD_EVAL_RUN_INDICES,
    Splits,
    build_splits,
    published_runs,
)
from pnvlad_service.data.splits.codec import (
    PACK_THRESHOLD,
    SPLITS_FORMAT,
    SPLITS_VERSION,
    load_splits,
    pack_lists,
    save_splits,
    splits_from_json,
    splits_to_json,
)
from pnvlad_service.data.splits.evaluation import (
    TRUTH_RADIUS,
    EvaluationSet,
    RunSubmaps,
    build_evaluation_set,
    build_evaluation_sets,
    evaluation_groups,
)
from pnvlad_service.data.splits.geometry import within_radius
from pnvlad_service.data.splits.pickles import (
    evaluation_from_pickles,
    evaluation_to_pickles,
    export_pickles,
    import_pickles,
    tuples_from_pickle,
)
from pnvlad_service.data.splits.regions import (
    HALF_SIZE,
    INHOUSE_CENTRES,
    OXFORD_CENTRES,
    REGIONS_FILE,
    REGIONS_FORMAT,
    TestRegions,
    builtin_regions,
    load_regions,
    published_regions_on,
    resolve_regions,
    save_regions,
)
from pnvlad_service.data.splits.tuples import (
    NEG_RADIUS,
    POS_RADIUS,
    TrainingTuples,
    build_training_tuples,
)

__all__ = [
    "HALF_SIZE",
    "INHOUSE_CENTRES",
    "NEG_RADIUS",
    "OXFORD_CENTRES",
    "OXFORD_EVAL_RUN_INDICES",
    "PACK_THRESHOLD",
    "POS_RADIUS",
    "REGIONS_FILE",
    "REGIONS_FORMAT",
    "SPLITS_FORMAT",
    "SPLITS_VERSION",
    "TRUTH_RADIUS",
    "EvaluationSet",
    "RunSubmaps",
    "Splits",
    "TestRegions",
    "TrainingTuples",
    "build_evaluation_set",
    "build_evaluation_sets",
    "build_splits",
    "build_training_tuples",
    "builtin_regions",
    "evaluation_from_pickles",
    "evaluation_groups",
    "evaluation_to_pickles",
    "export_pickles",
    "import_pickles",
    "load_regions",
    "load_splits",
    "pack_lists",
    "published_regions_on",
    "published_runs",
    "resolve_regions",
    "save_regions",
    "save_splits",
    "splits_from_json",
    "splits_to_json",
    "tuples_from_pickle",
    "within_radius",
]
