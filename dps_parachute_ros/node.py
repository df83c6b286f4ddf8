"""Placeholder entry point until its issue lands."""

import sys


def main(args=None) -> int:
    """Say that this executable is not implemented yet."""
    print('node: not implemented yet', file=sys.stderr)
    return 1


if __name__ == '__main__':
    sys.exit(main())
