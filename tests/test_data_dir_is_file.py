"""A data folder option that names a regular file says so ("is a file, not a folder"), not "does not exist":
`config.data.data_dir` (folder source) and `config.data.val_dir`, in the library and as bridge-train's one line."""
import pytest

from bridge_jax import train
from bridge_jax.data import folders, pipeline
from bridge_jax.eval import photometric


@pytest.fixture
def a_file(tmp_path):
    path = tmp_path / "frames.txt"
    path.write_text("left/0001.png right/0001.png\n")
    return path


def test_folder_source_and_val_dir_that_are_files(a_file, tmp_path):
    with pytest.raises(ValueError, match=rf"stereo video folder '{a_file}' is a file, not a folder; expected "):
        folders.folder_cycles(str(a_file))
    with pytest.raises(ValueError, match="is a file, not a folder"):
        pipeline.make_source(pipeline.DataConfig(source="folder", data_dir=str(a_file)))
    with pytest.raises(ValueError, match=rf"config\.data\.val_dir='{a_file}' is a file, not a folder \(held-out"):
        photometric.val_cycles(str(a_file), 8, 12, 4)
    # a path that is not there at all still says so
    with pytest.raises(ValueError, match="nope' does not exist"):
        folders.folder_cycles(str(tmp_path / "nope"))
    with pytest.raises(ValueError, match="nope' does not exist"):
        photometric.val_cycles(str(tmp_path / "nope"), 8, 12, 4)


@pytest.mark.parametrize("option", ["data_dir", "val_dir"])
def test_train_cli_is_one_line_exit_2_and_no_workdir(a_file, tmp_path, capsys, option):
    wd = tmp_path / "wd"
    data = [f"--config.data.data_dir={a_file}"] if option == "data_dir" else [f"--config.data.val_dir={a_file}"]
    rc = train.main(["--config=default:local", "--config.data.source=folder" if option == "data_dir" else
                     "--config.data.source=synthetic", *data, f"--workdir={wd}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error: "), err
    assert str(a_file) in err[0] and "is a file, not a folder" in err[0] and "does not exist" not in err[0]
    assert not wd.exists()
