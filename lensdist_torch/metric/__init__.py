"""The registration-quality metric, its loss and stateful metrics (docs/method.md, sections 2-5).

Modules: :mod:`~lensdist_torch.metric.quality` (maps and modules), :mod:`~lensdist_torch.metric.loss`,
:mod:`~lensdist_torch.metric.criteria` (per-pixel criteria and error images),
:mod:`~lensdist_torch.metric.pooling` (blocks and floor), :mod:`~lensdist_torch.metric.stateful`
(accumulating over a data set) and :mod:`~lensdist_torch.metric.classification`.
"""
