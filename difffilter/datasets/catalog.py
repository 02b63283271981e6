"""The registered data sets (sha256 of the files as distributed by the libRSF repository at commit
``d54801a2``; computed from the development copies, whose git blob hashes were checked against
upstream when they were copied)."""

from __future__ import annotations

from .registry import _CC_BY_SA, _RAW, DataSet, register

__all__ = ["LIBRSF_W3500", "SMARTLOC_BERLIN"]

_W3500_SHA = {
    "W3500_GT.txt": "9d19c28efaeabf24c6f5064b36d2b43a894f160c7b8d9198a25253701069797e",
    "W3500_heavy-tailed_Input.txt": "d4e6eac4ba28509f37672554bdfd96302ceed47306bdb86a8d3b2ccbb9e8ec23",
    "W3500_multimodal_Input.txt": "a47d15ef21efa9aa79c6248e0d67bad0867916335ab93ee59b84a2b0b7e1995b",
    "W3500_skewed_Input.txt": "4f02d32a23fda25bac7497ecbb524c96ec7ea29525895d19f1305025a1e5e111",
    "readme.txt": "6e94e76a63e4d6074cead2c272d616ab2c0ffd4d89056a8cafabd3f404b3d3ad",
    "LICENSE.txt": "7abe19ec9bb73b36141b999b861d24ad855e808bafe0f81e84cce28556f6c297",
}
_W3500_CITE = "T. Pfeifer (TU Chemnitz), libRSF ranging data sets (W3500, derived from GTSAM's W10000), CC BY-SA 4.0"

LIBRSF_W3500: dict[str, DataSet] = {}
for _variant in ("heavy-tailed", "multimodal", "skewed"):
    _input = f"W3500_{_variant}_Input.txt"
    _files = {k: _W3500_SHA[k] for k in (_input, "W3500_GT.txt", "readme.txt", "LICENSE.txt")}
    LIBRSF_W3500[_variant] = register(
        DataSet(
            name=f"librsf_w3500_{_variant.replace('-', '_')}",
            folder="librsf_ranging_w3500",
            files=_files,
            urls={k: f"{_RAW}/Ranging_Simulation/{k}" for k in _files},
            inputs=(_input,),
            truth="W3500_GT.txt",
            kind="ranging2d",
            licence=_CC_BY_SA,
            citation=_W3500_CITE,
            description=f"simulated 2-D ranging to 8 fixed anchors with odometry, 3500 steps, {_variant} range errors",
        )
    )

_SMARTLOC_FILES = {
    "Berlin_Potsdamer_Platz_Input.txt": "a4ba29c7b8c8c8c991a9194b09ed21527bcffd8c736affeb7ac8d7cb0ba730ff",
    "Berlin_Potsdamer_Platz_GT.txt": "247bc3f63f29a79411f557f5313e77ef2d054c780501c78ed98e563d4a3734ac",
    "upstream_readme.txt": "485d71cb25567d4c34de9475f6af9a867be6720c3ff0e330284c3986d0e755cc",
    "LICENSE.txt": "7abe19ec9bb73b36141b999b861d24ad855e808bafe0f81e84cce28556f6c297",
}
SMARTLOC_BERLIN = register(
    DataSet(
        name="smartloc_berlin_potsdamer",
        folder="smartloc_berlin_potsdamer",
        files=_SMARTLOC_FILES,
        urls={
            "Berlin_Potsdamer_Platz_Input.txt": f"{_RAW}/smartLoc/Berlin_Potsdamer_Platz_Input.txt",
            "Berlin_Potsdamer_Platz_GT.txt": f"{_RAW}/smartLoc/Berlin_Potsdamer_Platz_GT.txt",
            "upstream_readme.txt": f"{_RAW}/smartLoc/readme.txt",
            "LICENSE.txt": f"{_RAW}/smartLoc/LICENSE.txt",
        },
        inputs=("Berlin_Potsdamer_Platz_Input.txt",),
        truth="Berlin_Potsdamer_Platz_GT.txt",
        kind="pseudorange",
        licence=_CC_BY_SA,
        citation=(
            "P. Reisdorf, T. Pfeifer, J. Bressler, S. Bauer, P. Weissig, S. Lange, G. Wanielik, P. Protzel, "
            "'The Problem of Comparable GNSS Results - An Approach for a Uniform Dataset with Low-Cost and "
            "Reference Data', VEHICULAR 2016"
        ),
        description="real car drive, 283 s, u-blox pseudoranges + odometry + reference trajectory, Berlin Potsdamer Platz",
    )
)
