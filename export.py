"""Export rankings, descriptors and networks in the formats the field's tools read: ``locretrieval
export`` (`locretrieval.commands`), from a clone.

python export.py data=baidu model=precomputed model.feature_name=AP-GeM-LM18   # pairs files and descriptors
python export.py 'export=[onnx]' model=checkpoint model.weights=<run>/checkpoints/last.ckpt   # ONNX
"""

import sys

from locretrieval.commands import main

if __name__ == "__main__":
    main(["export", *sys.argv[1:]])
