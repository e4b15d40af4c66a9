"""Rankings (`Ranking`, relevance hits, random baselines), faiss search (`index.search`) and
the descriptor cache (`descriptors.describe_scene`).

Only `Ranking` and its helpers are imported here; import `locretrieval.retrieval.index` and
`locretrieval.retrieval.descriptors` where they are used (faiss and the models load there).
"""

from locretrieval.retrieval.ranking import EMPTY, Ranking, random_ranking, ranking_from_scores, relevant_hits, top_k

__all__ = ["EMPTY", "Ranking", "random_ranking", "ranking_from_scores", "relevant_hits", "top_k"]
