"""``python -m meshmei.benchmarks.reconstruct``: run the reconstruction benchmark (``--help`` for its options)."""

from .run import main

if __name__ == "__main__":
    main()
