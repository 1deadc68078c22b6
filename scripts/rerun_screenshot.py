"""Screenshot of a FroDO recording in Rerun's web viewer, in a real (headless) browser.

    apt-get install chromium && pip install --target /tmp/pw playwright   # once; neither is a project dependency
    rerun --serve-web --web-viewer-port 9090 --port 9877 out/demo/frodo.rrd &
    PYTHONPATH=/tmp/pw python scripts/rerun_screenshot.py docs/rerun_web_viewer.png

Loads the viewer page (served by `rerun --serve-web`), waits for the recording to stream in and draw
(software WebGL: SwiftShader), saves a screenshot and prints the browser's last console errors.
"""
from __future__ import annotations

import argparse
import sys
import time
from urllib.parse import quote

from playwright.sync_api import sync_playwright


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('out', help='PNG to write')
    parser.add_argument('--viewer', default='http://127.0.0.1:9090', help='web viewer URL (default: %(default)s)')
    parser.add_argument('--grpc', default='rerun+http://localhost:9877/proxy', help='recording server (default: %(default)s)')
    parser.add_argument('--wait', type=float, default=60.0, help='seconds to let the viewer load and draw')
    parser.add_argument('--chromium', default='/usr/bin/chromium', help='browser executable (default: %(default)s)')
    args = parser.parse_args()
    errors: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=args.chromium, headless=True,
                                    args=['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader'])
        page = browser.new_page(viewport={'width': 1600, 'height': 1000})
        page.on('console', lambda m: errors.append(m.text) if m.type == 'error' else None)
        page.goto(f'{args.viewer}/?url={quote(args.grpc, safe="")}')
        time.sleep(args.wait)
        page.screenshot(path=args.out)
        browser.close()
    print(f'wrote {args.out}; browser console errors: {len(errors)}')
    for line in errors[-10:]:
        print('  ' + line[:300])
    return 0


if __name__ == '__main__':
    sys.exit(main())
