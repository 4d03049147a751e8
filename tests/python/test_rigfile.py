"""Rig files in the Python client (issue 18): springblend.rigfile reads the bundled cylinder rig as the C++ CLI
does (an upload gives the CLI's character id), refuses bad rig files naming the file, the target and the field,
writes rigs that read back exactly, and a rig uploaded with upload_rig solves to the CLI's local frames."""

import json
import os
import tempfile
import unittest

import grpc
import numpy as np

import springblend
from springblend import rigfile
import springblend_testing as testing

RIG = str(testing.CYLINDER / "rig.json")
# bend (with an in-between at 0.5) and twist (masked); the combination bend_twist follows their product.
WEIGHTS = [[0.25, 0.5], [0.5, 0.0], [1.0, 1.0]]


def good_rig():
    """The bundled rig as JSON with absolute paths, for edits written into a temporary directory."""
    with open(RIG) as text:
        doc = json.load(text)
    absolute = lambda name: str(testing.CYLINDER / name)  # noqa: E731
    doc["rest"] = absolute(doc["rest"])
    for target in doc["targets"]:
        target["mesh"] = absolute(target["mesh"])
        for inbetween in target.get("inbetweens", []):
            inbetween["mesh"] = absolute(inbetween["mesh"])
        if isinstance(target.get("mask"), str):
            target["mask"] = absolute(target["mask"])
    return doc


class RigFileTest(unittest.TestCase):
    """No server needed."""

    def test_reads_the_bundled_rig(self):
        rig = rigfile.load_rig(RIG)
        self.assertEqual(rig.weight_names, ["bend", "twist"])
        self.assertEqual([t.name for t in rig.targets], ["bend", "twist", "bend_twist"])
        self.assertEqual(rig.rest.shape, (420, 3))
        self.assertEqual([w for w, _ in rig.targets[0].inbetweens], [0.5])
        self.assertEqual(rig.targets[1].mask.shape, (420,))
        self.assertEqual((rig.targets[1].mask.min(), rig.targets[1].mask.max()), (0.0, 1.0))
        self.assertEqual(rig.targets[2].combination, ["bend", "twist"])

    def test_bad_rig_files_name_file_target_and_field(self):
        def edit_mask(doc, directory):
            doc["targets"][1]["mask"] = os.path.join(directory, "short.txt")
            with open(doc["targets"][1]["mask"], "w") as out:
                out.write("1\n0\n")

        def bad_mask_line(doc, directory):
            doc["targets"][1]["mask"] = os.path.join(directory, "bad.txt")
            with open(doc["targets"][1]["mask"], "w") as out:
                out.write("1\nx1\n")

        cases = [
            ("unknown key", lambda d, _: d.update(rst=1), ["unknown key 'rst'"]),
            ("unknown target key", lambda d, _: d["targets"][1].update(maks="m"), ["targets[1]", "unknown key 'maks'"]),
            ("weight a string", lambda d, _: d["targets"][0]["inbetweens"][0].update(weight="half"),
             ["target 'bend': inbetweens[0].weight", "expected a number, got string"]),
            ("missing mesh", lambda d, _: d["targets"][0].update(mesh="nowhere.obj"),
             ["target 'bend': mesh", "file not found", "nowhere.obj"]),
            ("inline mask too short", lambda d, _: d["targets"][1].update(mask=[1.0] * 419),
             ["target 'twist': mask", "419 values", "420 vertices"]),
            ("mask file too short", edit_mask, ["target 'twist': mask", "2 values in", "short.txt"]),
            ("mask file bad line", bad_mask_line, ["target 'twist': mask", "bad.txt", "line 2", "'x1' is not a number"]),
            ("another topology", lambda d, _: d["targets"][1].update(mesh=str(testing.DATA / "cube" / "cube.obj")),
             ["target 'twist': mesh", "vertices, but the rest mesh has 420"]),
            ("combination not a list", lambda d, _: d["targets"][2].update(combination="bend"),
             ["target 'bend_twist': combination", "expected a list, got string"]),
            # Hardening IV, item 11: names that weights by name cannot address, and one product of weights twice.
            ("a name with '='", lambda d, _: d["targets"][1].update(name="twist=1"),
             ["targets[1].name 'twist=1'", "contains '='", "could not address it"]),
            ("a name with ','", lambda d, _: d["targets"][0].update(name="bend,left"),
             ["targets[0].name 'bend,left'", "contains ','"]),
            ("the same drivers twice",
             lambda d, _: d["targets"].append(dict(d["targets"][2], name="twist_bend", combination=["twist", "bend"])),
             ["target 'twist_bend': combination", "has the drivers of target 'bend_twist'"]),
        ]
        for what, edit, parts in cases:
            with self.subTest(what), tempfile.TemporaryDirectory() as directory:
                doc = good_rig()
                edit(doc, directory)
                path = os.path.join(directory, "rig.json")
                with open(path, "w") as out:
                    json.dump(doc, out)
                with self.assertRaises(springblend.SpringblendError) as caught:
                    rigfile.load_rig(path)
                self.assertEqual(caught.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
                for part in [path + ": "] + parts:
                    self.assertIn(part, caught.exception.message)

    def test_written_rig_reads_back_exactly(self):
        rig = rigfile.load_rig(RIG)
        with tempfile.TemporaryDirectory() as directory:
            again = rigfile.load_rig(rigfile.write_rig(os.path.join(directory, "copy.json"), rig))
        np.testing.assert_array_equal(again.rest, rig.rest)
        np.testing.assert_array_equal(again.faces, rig.faces)
        for a, b in zip(again.targets, rig.targets):
            self.assertEqual((a.name, a.combination), (b.name, b.combination))
            np.testing.assert_array_equal(a.positions, b.positions)
            self.assertEqual([w for w, _ in a.inbetweens], [w for w, _ in b.inbetweens])
            for (_, p), (_, q) in zip(a.inbetweens, b.inbetweens):
                np.testing.assert_array_equal(p, q)
            if b.mask is None:
                self.assertIsNone(a.mask)
            else:
                np.testing.assert_array_equal(a.mask, b.mask)

    def test_linear_blend_is_the_clis_linear_blendshape(self):
        # In-betweens (bend at 0.25 lies before its 0.5 in-between), a mask (twist) and the combination.
        rig = rigfile.load_rig(RIG)
        with tempfile.TemporaryDirectory() as directory:
            for i, w in enumerate([[0.25, 0.5], [0.75, 0.0], [1.0, 1.0], [1.3, -0.2]]):
                out = os.path.join(directory, f"lin{i}.obj")
                testing.cli("blend", "--rig", RIG, "--linear", "--weights", ",".join(map(str, w)), "--out", out)
                expected = testing.load_obj(out)[0]
                np.testing.assert_allclose(rigfile.linear_blend(rig, w), expected, rtol=0, atol=1e-5)
            np.testing.assert_array_equal(rigfile.linear_blend(rig, {"twist": 0.5}), rigfile.linear_blend(rig, [0, 0.5]))
        with self.assertRaises(springblend.SpringblendError) as caught:
            rigfile.linear_blend(rig, {"twirl": 1.0})
        self.assertIn("'twirl' is not a target of this rig (targets: bend, twist)", caught.exception.message)

    def test_a_baked_rig_plays_back_the_solved_frames(self):
        # springblend bake-rig --solved-inbetweens keeps solved frames as in-betweens and correctives; played
        # linearly they come back.
        with tempfile.TemporaryDirectory() as directory:
            summary = json.loads(testing.cli("bake-rig", "--rig", RIG, "--samples", "8", "--inbetweens", "2",
                                             "--solved-inbetweens", "--out", os.path.join(directory, "baked")))
            self.assertEqual(summary["inbetweens"], "solved")
            baked = rigfile.load_rig(summary["rig"])
            self.assertEqual(baked.weight_names, ["bend", "twist"])
            at = summary["targets"][1]["inbetweens"][0]
            frames = [[0.0, at], [1.0, 1.0], [0.4, 0.3]]
            solved = testing.cli_blend_rig(RIG, frames, directory)
            diagonal = testing.bounding_box_diagonal(baked.rest)
            for frame, expected in zip(frames[:2], solved[:2]):
                self.assertLess(np.abs(rigfile.linear_blend(baked, frame) - expected).max(), 1e-6 * diagonal)
            plain = rigfile.linear_blend(rigfile.load_rig(RIG), frames[2])
            self.assertLess(np.linalg.norm(rigfile.linear_blend(baked, frames[2]) - solved[2], axis=1).max(),
                            np.linalg.norm(plain - solved[2], axis=1).max())


class RigUploadTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.server = testing.Server()
        cls.client = springblend.Client(cls.server.address, timeout=180)
        cls.character = cls.client.upload_rig(RIG, name="cylinder rig")

    @classmethod
    def tearDownClass(cls):
        cls.client.close()
        cls.server.stop()

    def test_upload_gives_the_clis_character(self):
        c = self.character
        self.assertEqual(list(c.target_names), ["bend", "twist"])
        self.assertEqual(list(c.combination_names), ["bend_twist"])
        line = testing.cli("upload", "--server", self.server.address, "--rig", RIG).splitlines()[-1]
        self.assertEqual(json.loads(line)["id"], c.id)
        self.assertTrue(json.loads(line)["cache_hit"])

    def test_inbetweens_masks_and_combinations_change_the_id(self):
        rig = rigfile.load_rig(RIG)
        rig.targets[1].mask = None
        self.assertNotEqual(self.client.upload_rig(rig).id, self.character.id)
        rig = rigfile.load_rig(RIG)
        rig.targets[0].inbetweens = []
        self.assertNotEqual(self.client.upload_rig(rig).id, self.character.id)
        # A rig of plain targets is the plain upload's character.
        rig = rigfile.load_rig(RIG)
        plain = rigfile.Rig(rig.rest, rig.faces, [rigfile.Target(t.name, t.positions) for t in rig.targets[:2]])
        targets = {t.name: t.positions for t in plain.targets}
        self.assertEqual(self.client.upload_rig(plain).id, self.client.upload(rig.rest, rig.faces, targets).id)

    def test_uploads_are_routed_by_the_id_the_server_gives(self):
        # The routing header each upload carries (docs/server.md#routing) is the id the server answers with:
        # a production rig, the same rig with plain targets, and a plain upload with every build option.
        class Recorder:
            def __init__(self, method):
                self.method, self.routes = method, []

            def _record(self, metadata):
                self.routes.append(dict(metadata or ()).get(springblend.CHARACTER_HEADER))

            def __call__(self, request, **kwargs):
                self._record(kwargs.get("metadata"))
                return self.method(request, **kwargs)

            def future(self, request, **kwargs):
                self._record(kwargs.get("metadata"))
                return self.method.future(request, **kwargs)

        with springblend.Client(self.server.address, timeout=180) as client:
            recorder = Recorder(client._characters.UploadCharacter)
            client._characters.UploadCharacter = recorder
            rig = rigfile.load_rig(RIG)
            ids = [client.upload_rig(rig, no_target_paths=True).id]
            ids.append(client.upload_rig(rig, on_progress=lambda *_: None).id)
            targets = {t.name: t.positions for t in rig.targets[:2]}
            ids.append(client.upload(rig.rest, rig.faces, targets, fixed_vertices=[0, 5], static_tolerance=-1,
                                     no_interior=True, no_anchor=True, bending_stiffness=0.5,
                                     no_target_paths=True).id)
            ids.append(client.upload(rig.rest, rig.faces, targets, no_target_paths=True).id)
            ids.append(client.upload(rig.rest, rig.faces, targets, no_target_paths=True, hold_outer_rim=True).id)
            dense = client.upload(rig.rest, rig.faces, targets, path_intervals=8, path_max_samples=40)
            ids.append(dense.id)
        self.assertEqual(recorder.routes, ids)
        self.assertEqual(len(set(ids)), 6)
        self.assertLessEqual(dense.summary.path_samples, 2 * 40)  # two targets, at most 40 samples each
        # Each target's path, and where it is not certified, as weights low to high.
        self.assertEqual([p.target for p in dense.summary.paths], list(targets))
        self.assertEqual(sum(p.samples for p in dense.summary.paths), dense.summary.path_samples)
        for path in dense.summary.paths:
            self.assertLessEqual(len(path.uncertified_ranges), path.uncertified)
            for weights in path.uncertified_ranges:
                self.assertLess(weights.low, weights.high)

    def test_server_refusals_name_the_rig_file(self):
        rig = rigfile.load_rig(RIG)
        rig.targets[0].inbetweens = [(1.5, rig.targets[0].inbetweens[0][1])]
        with self.assertRaises(springblend.SpringblendError) as caught:
            self.client.upload_rig(rig)
        self.assertEqual(caught.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
        for part in [RIG + ": ", "target 'bend'", "inbetween_weights[0] = 1.5 is outside (0, 1)"]:
            self.assertIn(part, caught.exception.message)

    def test_frames_equal_the_clis_local_blend(self):
        solution = self.client.solve(self.character.id, WEIGHTS)
        self.assertTrue(solution.converged)
        with tempfile.TemporaryDirectory() as directory:
            local = testing.cli_blend_rig(RIG, WEIGHTS, directory)
            # The CLI's upload and solve through the server: the same frames again.
            remote, _ = testing.cli_solve(self.server.address, self.character.id, [{"weights": w} for w in WEIGHTS],
                                          [], directory)
        diagonal = testing.bounding_box_diagonal(local[0])
        self.assertLessEqual(np.abs(solution.positions - local).max(), 1e-5 * diagonal)
        self.assertLessEqual(np.abs(remote - local).max(), 1e-5 * diagonal)
        # Frame 1 is the in-between, frame 2 the combination's sculpt.
        half = testing.load_obj(testing.CYLINDER / "poses-2_cylinder-1.obj")[0]
        sculpt = testing.load_obj(testing.CYLINDER / "poses-2_cylinder-4.obj")[0]
        self.assertLessEqual(np.abs(local[1] - half).max(), 1e-5 * diagonal)
        self.assertLessEqual(np.abs(local[2] - sculpt).max(), 1e-5 * diagonal)


if __name__ == "__main__":
    unittest.main()
