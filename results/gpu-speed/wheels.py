"""The Python 3.12 wheels that the GPU machine lacks, slimmed to fit its 64 MiB carry limit:
`python results/gpu-speed/wheels.py [DEST]` (default `.whl` in the repository root, which git ignores).

The machine has torch, numpy, tensorboard and the usual scientific packages, but not dm_control, MuJoCo, shimmy,
gymnasium or tyro. dm_control's wheel is 56 MB and MuJoCo's 27 MB, mostly assets that no suite task reads (the
locomotion and dog models, test files, MuJoCo's experimental viewer): those files are left out of the copies."""
import os
import subprocess
import sys
import zipfile

# the versions the project's CPU environment runs (pip list there); all without their dependencies
WHEELS = ["dm_control==1.0.50", "mujoco==3.17.0", "shimmy==2.0.1", "gymnasium==1.4.0", "farama-notifications==0.0.6",
          "dm-env==1.6", "dm-tree==0.1.10", "glfw==2.11.0", "pyopengl==3.1.10", "tyro==1.0.17",
          "docstring-parser==0.18.0", "shtab==1.13.0", "typeguard==4.6.1"]
# folders no suite task imports or reads (cheetah-run and the other suite tasks but dog)
DROP = ("dm_control/locomotion/", "dm_control/suite/dog_assets/", "dm_control/mujoco/testing/", "dm_control/blender/",
        "dm_control/mjcf/test_assets/", "dm_control/suite/all_domains.png", "dm_control/third_party/kinova/",
        "mujoco/experimental/")
PLATFORMS = ["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_24_x86_64", "manylinux_2_17_x86_64",
             "manylinux2014_x86_64", "manylinux1_x86_64"]


def slim(path: str) -> int:
    """Rewrite the wheel at `path` without the files under DROP (and their RECORD lines). Returns files dropped."""
    kept, dropped = [], 0
    with zipfile.ZipFile(path) as source:
        for info in source.infolist():
            if info.filename.startswith(DROP):
                dropped += 1
                continue
            data = source.read(info)
            if info.filename.endswith(".dist-info/RECORD"):
                lines = data.decode().splitlines(keepends=True)
                data = "".join(line for line in lines if not line.startswith(DROP)).encode()
            kept.append((info, data))
    if dropped:
        with zipfile.ZipFile(path + ".tmp", "w", zipfile.ZIP_DEFLATED) as target:
            for info, data in kept:
                target.writestr(info, data)
        os.replace(path + ".tmp", path)
    return dropped


def main():
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    dest = sys.argv[1] if len(sys.argv) > 1 else os.path.join(root, ".whl")
    command = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--python-version", "3.12",
               "--implementation", "cp", "-d", dest, *[f"--platform={p}" for p in PLATFORMS], *WHEELS]
    subprocess.run(command, check=True)
    total = 0
    for name in sorted(os.listdir(dest)):
        path = os.path.join(dest, name)
        dropped = slim(path) if name.startswith(("dm_control-", "mujoco-")) else 0
        total += os.path.getsize(path)
        print(f"{os.path.getsize(path) / 2**20:6.1f} MiB {name}" + (f" ({dropped} files left out)" if dropped else ""))
    print(f"{total / 2**20:6.1f} MiB in all")


if __name__ == "__main__":
    main()
