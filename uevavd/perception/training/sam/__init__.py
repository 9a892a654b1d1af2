"""Training the ``sam`` segmenter's models: a small SAM from scratch (:mod:`.train_small`),
fine-tuning a checkpoint's mask decoder (:mod:`.finetune`), the loop and loss they share
(:mod:`.loop`), ground-truth views (:mod:`.data`), mask quality (:mod:`.evaluate`) and the
figures of docs/sam.md (:mod:`.report`)."""
