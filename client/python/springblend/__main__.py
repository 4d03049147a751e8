"""python -m springblend --version: the package's version (the project's, as springblend --version prints it)."""

import argparse
import sys


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m springblend",
                                     description="The springblend Python client (import springblend); see "
                                                 "docs/python.md. For the command line, use the springblend CLI.")
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    arguments = parser.parse_args(argv)
    import springblend
    if arguments.version:
        print(f"springblend {springblend.__version__}")
        return 0
    parser.print_help()
    return 0


if __name__ == "__main__":
    sys.exit(main())
