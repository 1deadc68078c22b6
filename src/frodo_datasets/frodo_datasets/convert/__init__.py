"""Dataset converters: play ScanNet, Redwood and TUM RGB-D sequences (and users' own folders) as contract bags.

    from frodo_datasets.convert import ConvertOptions, convert_tum
    summary = convert_tum('rgbd_dataset_freiburg1_xyz', 'fr1_xyz.mcap', ConvertOptions(views=35))
    print(summary.text())

`convert(format, input, output, options, progress=None, **reader_options)` dispatches on the format name
(`scannet`, `redwood`, `tum`, `folder`); the per-format functions take the reader's options as keywords
(see `read_scannet`, `read_redwood`, `read_tum`, `read_folder`). All return a `ConvertSummary` and raise
`ConvertError` with a message naming what is missing or wrong; a failed conversion leaves no output file.
"""
from __future__ import annotations

import os
from typing import Callable

from frodo_datasets.convert.common import ConvertError, ConvertOptions, ConvertSummary, Source
from frodo_datasets.convert.writer import write_bag

FORMATS = ('scannet', 'redwood', 'tum', 'folder')
Progress = Callable[[int], None] | None


def read_source(fmt: str, input_path: str | os.PathLike, options: ConvertOptions | None = None,
                **reader_options) -> Source:
    """The reader of `fmt` applied to `input_path`."""
    options = options or ConvertOptions()
    if fmt == 'tum':
        from frodo_datasets.convert.tum import read_tum
        return read_tum(input_path, **reader_options)
    if fmt == 'folder':
        from frodo_datasets.convert.folder import read_folder
        return read_folder(input_path, fps=options.fps, start_ns=options.start_ns, **reader_options)
    if fmt == 'redwood':
        from frodo_datasets.convert.redwood import read_redwood
        return read_redwood(input_path, fps=options.fps, start_ns=options.start_ns, **reader_options)
    if fmt == 'scannet':
        from frodo_datasets.convert.scannet import read_scannet
        return read_scannet(input_path, fps=options.fps, start_ns=options.start_ns,
                            with_instances=options.instances, with_ground_truth=options.ground_truth,
                            **reader_options)
    raise ConvertError(f'unknown format {fmt!r}; use one of {", ".join(FORMATS)}')


def convert(fmt: str, input_path: str | os.PathLike, output: str | os.PathLike,
            options: ConvertOptions | None = None, progress: Progress = None, **reader_options) -> ConvertSummary:
    """Read `input_path` as `fmt` and write the contract bag `output`."""
    options = options or ConvertOptions()
    source = read_source(fmt, input_path, options, **reader_options)
    return write_bag(source, output, options, progress)


def convert_tum(input_path, output, options: ConvertOptions | None = None, progress: Progress = None,
                **reader_options) -> ConvertSummary:
    """TUM RGB-D sequence -> contract bag (reader options: intrinsics, max_dt, depth_factor, trajectory)."""
    return convert('tum', input_path, output, options, progress, **reader_options)


def convert_folder(input_path, output, options: ConvertOptions | None = None, progress: Progress = None,
                   **reader_options) -> ConvertSummary:
    """Images + poses + intrinsics YAML -> contract bag (reader options: intrinsics, max_dt)."""
    return convert('folder', input_path, output, options, progress, **reader_options)


def convert_redwood(input_path, output, options: ConvertOptions | None = None, progress: Progress = None,
                    **reader_options) -> ConvertSummary:
    """Redwood sequence -> contract bag (reader options: trajectory, intrinsics, mesh, mesh_class)."""
    return convert('redwood', input_path, output, options, progress, **reader_options)


def convert_scannet(input_path, output, options: ConvertOptions | None = None, progress: Progress = None,
                    **reader_options) -> ConvertSummary:
    """ScanNet scene folder -> contract bag (reader options: labels_tsv, class_map, prefer)."""
    return convert('scannet', input_path, output, options, progress, **reader_options)


__all__ = ['FORMATS', 'ConvertError', 'ConvertOptions', 'ConvertSummary', 'Source', 'convert',
           'convert_folder', 'convert_redwood', 'convert_scannet', 'convert_tum', 'read_source', 'write_bag']
