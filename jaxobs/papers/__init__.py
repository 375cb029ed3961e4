"""The paper layer: reproductions of the sources, sweep scenarios and tuning problems, grouped by source
(``cortesao/``, ``grip2010/``, ``liu_peng/``) and listed in one registry (:mod:`jaxobs.papers.registry`) that the
``jaxobs`` command lists and runs. It imports the library; the library never imports it."""
