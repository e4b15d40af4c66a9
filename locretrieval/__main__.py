"""``python -m locretrieval``: the ``locretrieval`` command (`locretrieval.commands`)."""

from locretrieval.commands import main

if __name__ == "__main__":  # not in a worker process that imports the main module again
    main()
