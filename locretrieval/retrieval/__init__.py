"""Rankings, faiss search and the descriptor cache."""

from locretrieval.retrieval.ranking import EMPTY, Ranking, ranking_from_scores, top_k

__all__ = ["EMPTY", "Ranking", "ranking_from_scores", "top_k"]
