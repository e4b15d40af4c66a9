"""Rankings, faiss search and the descriptor cache.

`search` (faiss) and `describe_scene` / `validate_descriptors` (the models, torch) are loaded on
first use, so that code needing only `Ranking` (metrics, report) does not import them.
"""

import importlib

from locretrieval.retrieval.ranking import EMPTY, Ranking, random_ranking, ranking_from_scores, top_k

_LAZY = {"describe_scene": "descriptors", "validate_descriptors": "descriptors", "search": "index"}

__all__ = ["EMPTY", "Ranking", "random_ranking", "ranking_from_scores", "top_k", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f"locretrieval.retrieval.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
