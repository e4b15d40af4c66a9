"""Files models read and write: weight files (`weights`: where their authors publish them, content
hashes, safe loading, locretrieval checkpoints), descriptors read from kapture global-feature folders
(`precomputed`) and descriptors in other tools' formats (`feature_io`: kapture out, hloc in)."""
