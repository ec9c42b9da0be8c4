"""Make the tetrahedral meshes the shipped configs' diffusion truths are solved on.

fTetWild (pytetwild) is not deterministic: two runs on the same surface give meshes that
differ by a few % in node count, and so simulated images that differ from one clone to
the next. The meshes are therefore made once, by this script, and shipped in
data-samples/tetmesh/ under their content address (the subject surface's digest and the
target edge length); `simulate.flux.mesh_dir` points the configs at them.

    $ .venv/bin/python data-samples/make_tetmeshes.py configs/demo.yaml [configs/heights.yaml ...]
"""

from __future__ import annotations

import sys
from pathlib import Path


from fluxcli.config import load_config
from fluxcli.diffusion.mesh import tetrahedralize
from fluxcli.stages.plans import placer_of
from fluxcli.stages.capture import truth_config
from fluxcli.truth import tetmesh_key

HERE = Path(__file__).resolve().parent / "tetmesh"


def main(configs: list[str]) -> None:
    from fluxcli import artefacts as A

    HERE.mkdir(exist_ok=True)
    for c in configs:
        cfg = truth_config(load_config(c))  # the rig's true surface where the config captures its own
        surface = placer_of(cfg).surface
        edge = cfg.model.simulate.flux.mesh_edge_mm
        path = HERE / f"{tetmesh_key(surface, edge)}.h5"
        if path.is_file():
            print(f"{c}: {path.name} exists")
            continue
        nodes, tets = tetrahedralize(surface.vertices_mm, surface.faces, edge_length_mm=edge)
        with A.write_artefact(path, "tetmesh") as f:
            A.put(f, "nodes", nodes, compression="gzip", shuffle=True)
            A.put(f, "tets", tets.astype("int32"), compression="gzip", shuffle=True)
        print(f"{c}: {path.name}: {len(nodes)} nodes, {len(tets)} tets, {path.stat().st_size / 1e6:.1f} MB")


if __name__ == "__main__":
    main(sys.argv[1:] or ["configs/demo.yaml"])
