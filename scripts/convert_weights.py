"""Convert the authors' weight files into plain locretrieval checkpoints.

The output loads with ``torch.load(weights_only=True)`` and needs neither scipy's MATLAB
reader, scikit-learn nor TensorFlow; point ``model.weights`` at it.

    .venv/bin/python scripts/convert_weights.py netvlad Pitts30K_struct.mat netvlad_pitts30k.pt
    .venv/bin/python scripts/convert_weights.py apgem Resnet101-AP-GeM-LM18.pt apgem_lm18.pt
    .venv/bin/python scripts/convert_weights.py delg r101delg_gldv2clean_20200914/ delg_r101_gldv2.pt
    .venv/bin/python scripts/convert_weights.py delg-variables r101delg_gldv2clean_20200914/ --npz vars.npz

DELG needs tensorflow to read the SavedModel (``pip install 'locretrieval[tensorflow]'``), or an
``.npz`` of its variables made by ``delg-variables --npz`` on a machine that has it.
``delg-variables`` prints every variable name and shape: check them against the naming
`locretrieval.models.published.delg` assumes before trusting a conversion.
"""

import argparse

import numpy as np

import locretrieval  # noqa: F401
from locretrieval.models.published.apgem import convert_apgem
from locretrieval.models.published.delg import convert_delg, read_tf_variables
from locretrieval.models.published.netvlad import convert_netvlad


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    for name, help_text in (("netvlad", "struct .mat -> checkpoint"), ("apgem", "dirtorch .pt -> checkpoint")):
        command = commands.add_parser(name, help=help_text)
        command.add_argument("source")
        command.add_argument("destination")
    delg = commands.add_parser("delg", help="TF SavedModel folder or variables .npz -> checkpoint")
    delg.add_argument("source")
    delg.add_argument("destination")
    delg.add_argument("--gem-power", type=float, default=3.0)
    delg.add_argument(
        "--whitening-scope", default=None, help="TF scope of the whitening layer (default: found by shape)"
    )
    variables = commands.add_parser("delg-variables", help="list (and optionally dump) a TF model's variables")
    variables.add_argument("source")
    variables.add_argument("--npz", default=None, help="also write the variables to this .npz")
    args = parser.parse_args()

    if args.command == "netvlad":
        convert_netvlad(args.source, args.destination)
    elif args.command == "apgem":
        convert_apgem(args.source, args.destination)
    elif args.command == "delg":
        convert_delg(args.source, args.destination, args.gem_power, args.whitening_scope)
    else:
        found = read_tf_variables(args.source)
        for name in sorted(found):
            print(f"{name}\t{tuple(np.shape(found[name]))}\t{np.asarray(found[name]).dtype}")
        if args.npz:
            np.savez(args.npz, **found)
        return
    print(f"wrote {args.destination}")


if __name__ == "__main__":
    main()
