# gmmap: map server, robot agents and simulated fleets in one image; the entry point is `gmmap`.
#   docker build -t gmmap .    docker run --rm gmmap --help    docker compose up (docker-compose.yml)
FROM python:3.11-slim

WORKDIR /opt/gmmap
COPY pyproject.toml README.md ./
COPY gmm_core gmm_core
COPY protocol protocol
COPY services services
RUN pip install --no-cache-dir . \
    && useradd --create-home gmmap \
    && mkdir /data && chown gmmap /data

USER gmmap
WORKDIR /data
# numba's compiled kernels are cached here (site-packages is not writable for this user)
ENV NUMBA_CACHE_DIR=/home/gmmap/.cache/numba PYTHONUNBUFFERED=1
EXPOSE 8000
ENTRYPOINT ["gmmap"]
CMD ["--help"]
