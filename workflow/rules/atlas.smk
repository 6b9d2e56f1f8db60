# Stage 5: frames back-projected onto the mesh: textured 3-D model, 2-D atlas, coverage.


rule atlas:
    input:
        sfm="results/{subject}/{session}/sfm",
        preprocessed="results/{subject}/{session}/preprocessed",
        mesh="results/{subject}/{session}/mesh/surface.ply",
    output:
        atlas=report(
            directory("results/{subject}/{session}/atlas"),
            patterns=[r"{figure,(atlas|coverage)}.png"],
            caption="../report/atlas.rst",
            category="Atlases",
            subcategory="{subject}",
            labels={"session": "{session}", "figure": "{figure}"},
        ),
    params:
        atlas=config["atlas"],
        anatomy=session_anatomy,
    log:
        "logs/{subject}/{session}/atlas.log",
    benchmark:
        "benchmarks/{subject}/{session}/atlas.tsv"
    threads: session_threads(config["atlas"]["threads"])
    resources:
        mem_mb=6000,
        runtime=20,
    conda:
        CONDA_ENV
    script:
        "../../scripts/atlas.py"
