"""tuspy (the official Python tus client, PyPI `tuspy`) against `voxstream serve`, run by
server/tests/tus_clients.rs with the tools venv of scripts/schemathesis.sh:

    python tuspy_client.py create <endpoint> <file> <token> <scene-id> <chunk-bytes>
        creates the upload, sends the first chunk only and exits: the connection is cut.
        Prints the upload URL.
    python tuspy_client.py resume <endpoint> <upload-url> <file> <token> <chunk-bytes>
        a new process, as after a crash: resumes from the upload URL alone (tuspy asks HEAD for the
        offset) and sends the rest. Prints the offset it started from and the one it ended at.
"""

import sys

from tusclient import client


def main(argv):
    mode = argv[1]
    if mode == "create":
        endpoint, path, token, scene, chunk = argv[2:7]
        tus = client.TusClient(endpoint, headers={"Authorization": f"Bearer {token}"})
        uploader = tus.uploader(
            path,
            chunk_size=int(chunk),
            metadata={"filename": path.rsplit("/", 1)[-1], "id": scene},
        )
        uploader.upload_chunk()
        print(uploader.url)
    elif mode == "resume":
        endpoint, url, path, token, chunk = argv[2:7]
        tus = client.TusClient(endpoint, headers={"Authorization": f"Bearer {token}"})
        uploader = tus.uploader(path, url=url, chunk_size=int(chunk))
        start = uploader.offset
        uploader.upload()
        print(f"{start} {uploader.offset}")
    else:
        sys.exit(f"unknown mode {mode!r}")


if __name__ == "__main__":
    main(sys.argv)
