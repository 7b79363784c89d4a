# quadcast: one image for the three live processes (server, link, client); see docker-compose.yml.

# The browser viewer's npm dependency (fzstd), exactly as locked; copied into the package below.
FROM node:20-bookworm-slim AS viewer
WORKDIR /viewer
COPY server/viewer/package.json server/viewer/package-lock.json ./
RUN npm ci --no-audit --no-fund

FROM python:3.11-slim-bookworm

# Headless GL through Mesa's EGL (llvmpipe on machines without a GPU).
RUN apt-get update \
    && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends libegl1 libgl1-mesa-dri libegl-mesa0 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app
COPY pyproject.toml README.md ./
# quadcast/ holds the CLI and a symlink per layer folder (quadcast/server -> ../server, ...).
COPY quadcast quadcast
COPY protocol protocol
COPY codec codec
COPY render render
COPY transport transport
COPY server server
COPY --from=viewer /viewer/node_modules server/viewer/node_modules
COPY client client
COPY sim sim
RUN pip install --no-cache-dir .

ENTRYPOINT ["quadcast"]
CMD ["--help"]
