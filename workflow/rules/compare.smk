# Stage 6: co-register two sessions of a subject, difference their atlases, find changes.


rule compare:
    input:
        unpack(comparison_inputs),
    output:
        compare=directory("results/{subject}/compare/{a}_vs_{b}"),
    params:
        compare=config["compare"],
    log:
        "logs/{subject}/compare/{a}_vs_{b}.log",
    benchmark:
        "benchmarks/{subject}/compare/{a}_vs_{b}.tsv"
    threads: 2
    resources:
        mem_mb=6000,
        runtime=20,
    conda:
        CONDA_ENV
    script:
        "../../scripts/compare.py"
