# Stage 3: features, pairs, mapping with bundle adjustment; poses and sparse cloud in mm.


rule sfm:
    input:
        preprocessed="results/{subject}/{session}/preprocessed",
    output:
        sfm=directory("results/{subject}/{session}/sfm"),
    params:
        sfm=config["sfm"],
        extent_mm=lambda wc: session_scale(wc)["extent_mm"],
        volume_ml=lambda wc: session_scale(wc)["volume_ml"],
    log:
        "logs/{subject}/{session}/sfm.log",
    benchmark:
        "benchmarks/{subject}/{session}/sfm.tsv"
    threads: session_threads(config["sfm"]["num_threads"])
    resources:
        mem_mb=6000,
        runtime=30,
    conda:
        CONDA_ENV
    script:
        "../../scripts/sfm.py"
