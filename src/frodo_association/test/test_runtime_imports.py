"""A robot install runs the association node without the renderer: the node and the runtime modules must not
import frodo_datasets (only the evaluation's rendered-furniture scenes do, lazily)."""
import subprocess
import sys


def test_node_and_core_do_not_import_frodo_datasets():
    code = ('import sys, frodo_association.association_node, frodo_association.core, frodo_association.evaluate; '
            'print(sorted(m for m in sys.modules if m.startswith("frodo_datasets")))')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == '[]', out.stdout
