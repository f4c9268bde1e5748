"""``python -m msmem_sapien``: which camera the SAPIEN backend will use here, and why."""

from msmem_sapien.camera import lavapipe_icd, native_renderer


def main() -> None:
    ok, detail = native_renderer()
    icd = lavapipe_icd()
    print(f"camera: {'native' if ok else 'raycast'} ({detail})")
    print(f"lavapipe from setup_lavapipe.sh: {icd or 'not installed'}")


if __name__ == "__main__":
    main()
