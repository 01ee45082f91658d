"""lab/scripts/blob_ranker.py judges the score tie-break on a select study's recorded blobs."""
import csv
import json
import math

from lab_scripts import load

ranker = load("blob_ranker")


def blob(response, peak, roundness, on):
    return {"blob": {"response": response, "scale_mm": 6.0}, "on_nodule": on,
            "region": {"roundness": roundness, "diameter_mm": 12.0, "peak_score": peak}}


def write_study(root, sets):
    """sets: {set: {patient: (diameter_mm, [blob, ...])}} as select_study.py lays them out."""
    for set_name, patients in sets.items():
        (root / set_name).mkdir(parents=True)
        with open(root / set_name / "results.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["patient", "gt_diameter_mm"])
            for patient, (diameter, blobs) in patients.items():
                w.writerow([patient, diameter])
                (root / set_name / patient).mkdir()
                result = {"centres": {"blind_accepted": blobs}}
                (root / set_name / patient / "result.json").write_text(json.dumps(result))


def test_the_score_prefers_response_per_peak_then_roundness_among_the_top_few():
    # A dense speck answers most strongly; the nodule answers less, but more per unit of peak.
    speck, nodule = ((math.log(1.0 / 1.0), 0.5), False), ((math.log(0.6 / 0.2), 0.5), True)
    assert ranker.takes_nodule([speck, nodule], weight=0.0, top=2)
    assert not ranker.takes_nodule([speck, nodule], weight=0.0, top=1), "only the top few contend"
    # Roundness settles two alike per unit of peak.
    drawn, round_ = ((0.0, 0.2), False), ((-0.1, 0.9), True)
    assert not ranker.takes_nodule([drawn, round_], weight=0.0, top=2)
    assert ranker.takes_nodule([drawn, round_], weight=1.0, top=2)
    assert not ranker.takes_nodule([], weight=1.0, top=5)


def test_cases_read_nodules_of_ten_mm_or_more_and_patients_are_held_out_together(tmp_path):
    drawn_first = [blob(1.0, 0.5, 0.2, False), blob(0.95, 0.5, 0.9, True)]
    write_study(tmp_path, {
        "consensus-1": {"LIDC-IDRI-0001": (14.0, drawn_first), "LIDC-IDRI-0002": (8.0, drawn_first)},
        "consensus-2": {"LIDC-IDRI-0001": (14.0, drawn_first), "LIDC-IDRI-0003": (20.0, drawn_first)},
        "spheres-1": {"LIDC-IDRI-0001": (12.0, drawn_first)},
    })
    found = ranker.cases(str(tmp_path), "blind")
    assert [(s, p) for s, p, _ in found] == [
        ("consensus-1", "LIDC-IDRI-0001"), ("consensus-2", "LIDC-IDRI-0001"), ("consensus-2", "LIDC-IDRI-0003"),
        ("spheres-1", "LIDC-IDRI-0001")]
    # The same phantom patient in two anatomies is one group; a sphere is its own.
    groups = {ranker.group_of(s, p) for s, p, _ in found}
    assert groups == {"LIDC-IDRI-0001", "LIDC-IDRI-0003", "spheres-1/LIDC-IDRI-0001"}
    # Every case needs roundness to take the nodule: every fold chooses a weight > 0 and wins.
    taken, chosen = ranker.leave_one_patient_out(found, top=5)
    assert taken == 4 and all(w > 0 for w in chosen) and len(chosen) == 3
