"""Tabs between YAML tokens read as whitespace, as yaml-cpp (nav2 map_server's YAML reader) reads
them: `YamlCppWhitespace`, a mixin for a PyYAML loader.

yaml-cpp's `Scanner::ScanToNextToken` skips tabs between tokens as it skips spaces (taking no simple
key after one in a block's indentation); PyYAML's `scan_to_next_token` skips spaces only, and stops at
a tab after a colon, before a comment or at the end of a line ("found character '\\t' that cannot
start any token"). A hand-edited map.yaml with one loads in map_server, so the service's import
(`nav2_import`) and the client that zips a map.yaml for it (`fleetmap_client.rest.nav2_files_zip`)
read it as map_server does. Pure: yaml only.
"""

from __future__ import annotations

import yaml


class YamlCppWhitespace(yaml.reader.Reader, yaml.scanner.Scanner):
    """Put before a PyYAML loader class in a loader's bases (`class L(YamlCppWhitespace,
    yaml.SafeLoader)`): its scanner then skips tabs between tokens as spaces."""

    def scan_to_next_token(self) -> None:
        """PyYAML's skip of what lies between two tokens (spaces, comments, line breaks), with tabs
        skipped as spaces. A tab in a block's indentation makes no key there, as in yaml-cpp, which
        takes no simple key after one: PyYAML then refuses what follows, as yaml-cpp does."""
        if self.index == 0 and self.peek() == "\ufeff":
            self.forward()
        while True:
            while self.peek() in " \t":
                if self.peek() == "\t" and not self.flow_level:
                    self.allow_simple_key = False
                self.forward()
            if self.peek() == "#":
                while self.peek() not in "\0\r\n\x85\u2028\u2029":
                    self.forward()
            if not self.scan_line_break():
                return
            if not self.flow_level:
                self.allow_simple_key = True


__all__ = ["YamlCppWhitespace"]
