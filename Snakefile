# cystomap: monocular cystoscopy video -> 3-D model, 2-D atlas, and changes between sessions.
# Run the default study (the built-in phantom):   snakemake --cores 2
# Run your own study:                             snakemake --cores 2 --configfile my_study.yaml
from pathlib import Path

from snakemake.utils import min_version

min_version("9.0")


# The repository's config.yaml is always the base; --configfile files are merged over it.
configfile: Path(workflow.basedir) / "config.yaml"


# `snakemake --report report.html` (or .zip): atlases, change maps and tables, with captions.
report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/phantom.smk"
include: "workflow/rules/frames.smk"
include: "workflow/rules/preprocess.smk"
include: "workflow/rules/sfm.smk"
include: "workflow/rules/mesh.smk"
include: "workflow/rules/atlas.smk"
include: "workflow/rules/compare.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/report.smk"


rule all:
    input:
        all_targets(),
    default_target: True
