"""The procedural street scenes: the embedded default dataset (nothing to download).

:mod:`~costseg.data.toy.dataset` is the Dataset; :mod:`~costseg.data.toy.scene` lays out one
scene from :mod:`~costseg.data.toy.street`, :mod:`~costseg.data.toy.scenery` and
:mod:`~costseg.data.toy.traffic`; :mod:`~costseg.data.toy.draw` and
:mod:`~costseg.data.toy.photo` paint it.
"""

from costseg.data.toy.dataset import StreetScenes, render_scene

__all__ = ["StreetScenes", "render_scene"]
