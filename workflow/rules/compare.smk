# Stage 6: co-register two sessions of a subject, difference their atlases, find changes.


rule compare:
    input:
        unpack(comparison_inputs),
    output:
        compare=report(
            directory("results/{subject}/compare/{a}_vs_{b}"),
            patterns=[
                r"{file,(difference|changes|side_by_side|landmarks)\.png|(changes|landmarks|findback)\.csv"
                r"|findback/change\d+_(atlas|frame)_[ab]\.png}"
            ],
            caption="../report/compare.rst",
            category="Changes",
            subcategory="{subject}",
            labels={"comparison": "{a} vs {b}", "file": "{file}"},
        ),
    params:
        compare=config["compare"],
        landmarks=lambda w: landmarks_of(w.subject, w.a),
    log:
        "logs/{subject}/compare/{a}_vs_{b}.log",
    benchmark:
        "benchmarks/{subject}/compare/{a}_vs_{b}.tsv"
    threads: config["compare"]["threads"]
    resources:
        mem_mb=6000,
        runtime=20,
    conda:
        CONDA_ENV
    script:
        "../../scripts/compare.py"
