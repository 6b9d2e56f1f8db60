# Stage 2: undistort, mask the field of view, level brightness, enhance contrast.


rule preprocess:
    input:
        frames="results/{subject}/{session}/frames",
    output:
        preprocessed=directory("results/{subject}/{session}/preprocessed"),
    params:
        preprocess=config["preprocess"],
        camera=session_camera,
    log:
        "logs/{subject}/{session}/preprocess.log",
    benchmark:
        "benchmarks/{subject}/{session}/preprocess.tsv"
    threads: session_threads(config["preprocess"]["threads"])
    resources:
        mem_mb=2000,
        runtime=20,
    conda:
        CONDA_ENV
    script:
        "../../scripts/preprocess.py"
