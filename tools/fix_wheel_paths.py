"""Rewrite include paths baked into the ROS 2 wheels' CMake files for this interpreter.

The PyPI wheels export CMake targets with the include directories of the machine that built them
(``/opt/python/cp311-cp311/include/python3.11`` and that machine's numpy headers). CMake refuses
targets that name a non-existent path, so they are pointed at this interpreter's own.
"""

import pathlib
import re
import sys
import sysconfig

import numpy


def main(prefix: str) -> int:
    """Fix every *.cmake file under `prefix`/share; print how many changed."""
    python_include = sysconfig.get_paths()['include']
    numpy_include = numpy.get_include()
    patterns = [
        (re.compile(r'/opt/python/cp3\d+-cp3\d+/include/python3\.\d+'), python_include),
        (re.compile(r'/opt/python/cp3\d+-cp3\d+/lib/python3\.\d+/site-packages/numpy/'
                    r'(?:_core|core)/include'), numpy_include),
    ]
    changed = 0
    for path in pathlib.Path(prefix, 'share').rglob('*.cmake'):
        text = path.read_text(errors='surrogateescape')
        new = text
        for pattern, replacement in patterns:
            new = pattern.sub(replacement, new)
        if new != text:
            path.write_text(new, errors='surrogateescape')
            changed += 1
    print(f'fixed include paths in {changed} CMake files')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1]))
