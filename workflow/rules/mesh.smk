# Stage 4: a closed, watertight surface mesh of the wall from the sparse cloud.


rule mesh:
    input:
        sfm="results/{subject}/{session}/sfm",
    output:
        ply="results/{subject}/{session}/mesh/surface.ply",
        json="results/{subject}/{session}/mesh/mesh.json",
    params:
        mesh=config["mesh"],
    log:
        "logs/{subject}/{session}/mesh.log",
    benchmark:
        "benchmarks/{subject}/{session}/mesh.tsv"
    threads: session_threads(2)
    resources:
        mem_mb=3000,
        runtime=10,
    conda:
        CONDA_ENV
    script:
        "../../scripts/mesh.py"
