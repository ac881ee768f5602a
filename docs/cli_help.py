"""The ``cli-help`` directive: the help text of a ``robust-sindy`` command, as argparse
prints it (so the CLI page cannot drift from the parser)."""

import contextlib
import io

from docutils import nodes
from sphinx.util.docutils import SphinxDirective

from robust_sindy.cli import main


class CliHelp(SphinxDirective):
    optional_arguments = 1

    def run(self):
        argv = [*self.arguments[0].split(), "--help"] if self.arguments else ["--help"]
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
            main(argv)
        text = out.getvalue()
        block = nodes.literal_block(text, text)
        block["language"] = "text"
        return [block]


def setup(app):
    app.add_directive("cli-help", CliHelp)
    return {"parallel_read_safe": True}
