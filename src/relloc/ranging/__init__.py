"""Learned UWB range-error correction: one model per transceiver pair (the paper's ``PF_UL``).

Modules, and what each needs:

* :mod:`~relloc.ranging.dataset` (NumPy): ranging CSV loading and validation, repeat removal,
  splits by blocks of time, windows.
* :mod:`~relloc.ranging.inference` (onnxruntime): trained model directories at run time.
* :mod:`~relloc.ranging.evaluate` (onnxruntime): models against the zero and per-pair bias
  baselines.
* :mod:`~relloc.ranging.manifest`: the model directory layout and its ``manifest.json``.
* :mod:`~relloc.evaluation.range_errors` (outside this package, above the sources): a ranging CSV
  from a recording with motion capture.
* :mod:`~relloc.ranging.synthetic`: CSVs with a known orientation-dependent error.
* :mod:`~relloc.ranging.models`, :mod:`~relloc.ranging.train`, :mod:`~relloc.ranging.export`
  (torch, the optional extra ``relloc[train]``): stacked LSTM, bidirectional LSTM and ConvLSTM,
  their training and ONNX export.
* :mod:`~relloc.cli.ranging`: ``relloc ranging train | eval | export | bag-csv``.

The run-time stage is :class:`relloc.stages.range_correction.RangeCorrector`. Importing this
package (or anything but the three torch modules) never imports torch. See docs/explanation/range-correction.md.
"""
