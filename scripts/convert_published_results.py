"""Convert kapture-localization's published benchmark tables (AsciiDoc) into the CSVs of
``locretrieval/report/published/``.

The sources are ``doc/benchmark_results_{aachen,baidu,gangnam,robotcar}.adoc`` of
https://github.com/naver/kapture-localization (the commit is in ``published/SOURCES.md``):

    .venv/bin/python scripts/convert_published_results.py benchmark_results_aachen.adoc aachen \\
        locretrieval/report/published/aachen.csv

Each ``== <local feature> Results`` section holds one table per paradigm (``=== global_sfm``,
``=== local_sfm``, ``=== EWB``); a table has a column of global feature names, a column of k,
then per query condition (``day``/``night``, ``test``/``validation``; a table without
conditions covers all queries) a column per accuracy threshold and, for some, the median
position and rotation errors. Every percentage is written as it is printed; ``inf`` medians
(fewer than half of the queries localized) stay ``inf``.
"""

import argparse
from pathlib import Path

from locretrieval.report.published import parse_adoc


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="a benchmark_results_<dataset>.adoc file")
    parser.add_argument("dataset", help="the locretrieval dataset name (configs/data/<name>.yaml)")
    parser.add_argument("destination", type=Path, help="the CSV to write")
    arguments = parser.parse_args()
    table = parse_adoc(arguments.source.read_text(), arguments.dataset, str(arguments.source))
    table.to_csv(arguments.destination, index=False)
    print(f"{arguments.destination}: {len(table)} rows")


if __name__ == "__main__":
    main()
