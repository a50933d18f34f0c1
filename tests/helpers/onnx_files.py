"""ONNX files that do not reproduce their model, for the tests of the export's own check."""

from __future__ import annotations


def corrupt_exports(monkeypatch) -> None:
    """Make ``s3k.inference.export`` change one weight of every file it exports, after writing it: the
    export's check must then refuse the file."""
    import numpy as np
    import onnx
    from onnx import numpy_helper

    import s3k.inference.export as export

    original = export.export_module

    def export_then_corrupt(*args, **kwargs):
        path = original(*args, **kwargs)
        model = onnx.load(str(path))
        init = max(model.graph.initializer, key=lambda t: int(np.prod(t.dims)))
        arr = numpy_helper.to_array(init).copy()
        arr.flat[0] += 1.0
        init.CopyFrom(numpy_helper.from_array(arr, init.name))
        onnx.save(model, str(path))
        return path

    monkeypatch.setattr(export, "export_module", export_then_corrupt)
