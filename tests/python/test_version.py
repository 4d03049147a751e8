"""The package's version is the project's (CMakeLists.txt project(VERSION)), as the C++ programs print it."""

import os
import unittest

import springblend


class VersionTest(unittest.TestCase):
    def test_version_is_the_projects(self):
        self.assertEqual(springblend.__version__, os.environ["SPRINGBLEND_VERSION"])


if __name__ == "__main__":
    unittest.main()
