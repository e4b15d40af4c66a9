"""Rankings, faiss search and the descriptor cache."""

from locretrieval.retrieval.descriptors import describe_scene, validate_descriptors
from locretrieval.retrieval.index import search
from locretrieval.retrieval.ranking import EMPTY, Ranking, random_ranking, ranking_from_scores, top_k

__all__ = [
    "EMPTY",
    "Ranking",
    "describe_scene",
    "random_ranking",
    "ranking_from_scores",
    "search",
    "top_k",
    "validate_descriptors",
]
